"""Where a benchmark's figures came from: the commit, the machine, the libraries, the date and the command.

Every benchmark writes ``provenance()`` into its raw JSON, so a table in ``docs/benchmarks.md`` or
``docs/analysis.md`` can be checked against the run that made it (issue 29 §4).
"""

from __future__ import annotations

import datetime as dt
import os
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# the numerical libraries the figures depend on: the dependencies are ranges, and a rendered, reconstructed
# re-scan set differed between two installs of the same commit (docs/analysis.md §6)
LIBRARIES = ("numpy", "scipy", "numba", "opencv-python-headless", "open3d-cpu", "pycolmap", "Django", "celery")


def commit() -> str:
    """The short hash of the checkout the benchmark runs from ("?" outside git), "+dirty" if it has changes."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "?"
    return head + ("+dirty" if dirty else "")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> str:
    """Cores, CPU model, memory (GiB), system and Python, in one line."""
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return (f"{os.cpu_count()} cores ({cpu_model()}), {mem:.0f} GiB RAM, {platform.system()} {platform.release()}, "
            f"Python {platform.python_version()}")


def library_versions() -> dict:
    """The installed versions of ``LIBRARIES`` (those not installed are left out)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in LIBRARIES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            pass
    return out


def load_average() -> list:
    """The 1, 5 and 15 minute load averages now: other work sharing the cores shows here."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def provenance(script: str, argv: list | None = None) -> dict:
    """``script``'s (``__file__``) command line with ``argv`` (default: the process's), its commit, commit, machine, libraries, date (UTC) and load average.

    Call it as the run starts: the commit is then the code that was loaded (HEAD may move during an hour's run),
    and the date and the load average are the start's."""
    args = list(sys.argv[1:] if argv is None else argv)
    name = script
    try:
        name = str(Path(script).resolve().relative_to(ROOT))
    except ValueError:
        pass
    return {"command": " ".join([".venv/bin/python", name, *args]), "commit": commit(), "machine": machine(),
            "libraries": library_versions(),
            "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "load_average_at_start": load_average()}
