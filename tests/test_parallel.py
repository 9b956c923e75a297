"""Process-level settings of the engine's stages."""

import os
import platform

import numpy as np
import pytest

from recon_engine.parallel import cores, reuse_freed_images


def test_cores_is_the_request_or_one_per_core(monkeypatch):
    monkeypatch.delenv("TORSOSCAN_THREADS", raising=False)
    assert cores(3) == 3
    assert cores(0) >= 1


def test_a_thread_budget_in_the_environment_caps_the_default(monkeypatch):
    # a clinic worker running two arm tasks side by side on 2 cores gives each task 1 thread
    monkeypatch.setenv("TORSOSCAN_THREADS", "1")
    assert cores(0) == 1
    assert cores(3) == 3  # an explicit request is the caller's
    monkeypatch.setenv("TORSOSCAN_THREADS", "zero")  # not a count: ignored
    assert cores(0) == (os.cpu_count() or 1)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")
def test_it_keeps_freed_large_images_for_reuse():
    assert reuse_freed_images() is True
    # large blocks still allocate, free and come back intact
    for _ in range(3):
        a = np.ones((2000, 3000, 4), np.float32)
        assert float(a[-1, -1, -1]) == 1.0
        del a


# glibc maps a block above its mmap threshold (at most 32 MB by default) afresh; reuse_freed_images raises the
# threshold to 512 MB. A fresh process allocates 64 MB and reports whether glibc mapped it: that is the setting
_PROBE = """
import ctypes, sys
import numpy as np
sys.path.insert(0, {root!r})

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                 "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
{call}
before = libc.mallinfo2().hblkhd
block = np.ones(64 << 20, np.uint8)
print("mapped" if libc.mallinfo2().hblkhd - before >= 64 << 20 else "heap")
"""

_LIBRARY_CALL = """
from recon_engine.formats import rig_from_dict
from recon_engine.reconstruction import reconstruct_arm
from tests.boundary_fixtures import RIG
try:
    reconstruct_arm(None, rig_from_dict(RIG), None, "no such arm")  # gets past where it tuned the allocator
except ValueError as exc:
    assert "no arm" in str(exc)
"""


def _allocator_after(call):
    import subprocess
    import sys
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[1])
    out = subprocess.run([sys.executable, "-c", _PROBE.format(root=root, call=call)], capture_output=True, text=True,
                         cwd=root, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")
def test_a_library_call_leaves_the_processes_allocator_alone():
    # the probe sees the setting: the opt-in moves a 64 MB block onto the heap
    assert _allocator_after("from recon_engine.parallel import reuse_freed_images; reuse_freed_images()") == "heap"
    assert _allocator_after(_LIBRARY_CALL) == "mapped"


def test_the_reconstruction_commands_opt_in_and_calibration_does_not(monkeypatch, tmp_path):
    from recon_engine import cli, parallel

    calls = []
    monkeypatch.setattr(parallel, "reuse_freed_images", lambda *a, **k: calls.append(1) or True)
    missing = str(tmp_path / "missing.json")
    for command in (["reconstruct-arm", "--arm", "A", "--out", str(tmp_path / "a.ply")],
                    ["reconstruct", "--out", str(tmp_path / "torso")]):
        assert cli.main([command[0], "--rig", missing, "--calibration", missing, *command[1:], str(tmp_path)]) == 2
    assert len(calls) == 2
    assert cli.main(["calibrate", "--rig", missing, "--testfield", missing, "--out", missing, str(tmp_path)]) == 2
    assert len(calls) == 2
