"""Benchmark: the README's `make test` on a fresh clone, as a new user's machine runs it.

    .venv/bin/python benchmarks/bench_suite.py --json docs/results/bench_suite.json

Clones this repository's checked-out branch into a new temporary folder (nothing beside it: no ``../shared``,
no ``.venv``, no ``bench-out``), runs ``CI=true make test`` there and records the wall time (installation
included), pytest's own time, the outcome counts and the slowest tests, with the run's provenance. The
clone is removed afterwards unless ``--keep``. The brief's limit is 15 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from provenance import ROOT, provenance  # noqa: E402

# pytest's last line, e.g. "587 passed, 1 skipped, 3 warnings in 553.21s (0:09:13)"
SUMMARY = re.compile(r"^=*\s*(?P<counts>(?:\d+ \w+(?:, )?)+) in (?P<seconds>[\d.]+)s")
# --durations lines, e.g. "140.12s call     tests/test_clinic_day.py::test_it_runs_a_clinic_day"
DURATION = re.compile(r"^(?P<seconds>[\d.]+)s (?P<phase>setup|call|teardown)\s+(?P<test>\S+)")


def parse_pytest(log: str) -> dict:
    """The outcome counts, pytest's own seconds and the slowest tests from a ``make test`` log."""
    counts, seconds, slowest = {}, None, []
    for line in log.splitlines():
        m = SUMMARY.match(line.strip())
        if m:
            seconds = float(m["seconds"])
            counts = {w: int(n) for n, w in (c.split(" ", 1) for c in m["counts"].split(", "))}
        d = DURATION.match(line.strip())
        if d:
            slowest.append({"seconds": float(d["seconds"]), "phase": d["phase"], "test": d["test"]})
    return {"counts": counts, "pytest_s": seconds, "slowest": slowest}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default="bench-out/bench_suite.json", help="where to write the figures")
    ap.add_argument("--keep", action="store_true", help="keep the clone (its folder is printed)")
    args = ap.parse_args(argv)
    run = provenance(__file__, argv)
    parent = Path(tempfile.mkdtemp(prefix="torsoscan-clone-"))
    clone = parent / "torsoscan"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, capture_output=True,
                            text=True, check=True).stdout.strip()
    print(f"clone of {commit} in {clone}; ../shared beside it: {(parent / 'shared').exists()}", flush=True)
    env = {**os.environ, "CI": "true"}
    env.pop("VIRTUAL_ENV", None)
    t0 = time.perf_counter()
    proc = subprocess.run(["make", "test"], cwd=clone, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    log = proc.stdout + proc.stderr
    (clone.parent / "make-test.log").write_text(log)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = {**run, "clone_commit": commit, "shared_beside_clone": (parent / "shared").exists(),
              "returncode": proc.returncode, "wall_s": round(wall, 1),
              "cpu_s": {"user": round(children.ru_utime, 1), "system": round(children.ru_stime, 1)},
              "test_workers": os.environ.get("TEST_WORKERS", f"nproc + 1 = {(os.cpu_count() or 1) + 1}"),
              **parse_pytest(log)}
    dest = Path(args.json)
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(result, indent=2))
    print("\n".join(log.splitlines()[-25:]))
    print(f"make test: rc {proc.returncode}, {wall:.0f} s wall, pytest {result['pytest_s']} s, {result['counts']}")
    print(f"raw figures: {dest}; log: {clone.parent / 'make-test.log'}")
    if not args.keep:
        shutil.rmtree(clone, ignore_errors=True)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
