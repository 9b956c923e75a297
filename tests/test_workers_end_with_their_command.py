"""A killed command leaves none of its worker processes behind: the simulator's render workers went on for
minutes after ``torsoscan simulate`` was killed, taking the cores from whatever ran next."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from recon_engine import parallel


def children(pid):
    """Live (not zombie) processes whose parent is ``pid``."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(d.name))
    return out


def alive(pid):
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2:].split()[0] != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_the_render_workers_end_when_simulate_is_killed(tmp_path):
    exe = Path(sys.executable).with_name("torsoscan")
    workers = []
    proc = subprocess.Popen([str(exe), "simulate", "--preset", "tiny", "--seed", "5", "--out", str(tmp_path / "s")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            # the spawn start method adds a resource tracker; the render workers are the others
            workers = children(proc.pid)
            if len(workers) >= 2:
                break
            time.sleep(0.2)
        assert proc.poll() is None and len(workers) >= 2, "the simulator did not start its workers"
        time.sleep(1.0)  # let them reach their initializer
        workers = children(proc.pid)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and any(alive(w) for w in workers):
            time.sleep(0.2)
        left = [w for w in workers if alive(w)]
        assert not left, f"worker processes {left} outlived their command"
    finally:
        if proc.poll() is None:
            proc.kill()
        for w in workers:
            if alive(w):
                os.kill(w, signal.SIGKILL)


def test_it_reports_where_the_signal_is_not_available(monkeypatch):
    monkeypatch.setattr("ctypes.CDLL", lambda *a, **k: (_ for _ in ()).throw(OSError("no libc")))
    assert parallel.die_with_parent() is False
