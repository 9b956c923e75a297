"""Benchmark: one whole visit (``torsoscan reconstruct``) timed, with the memory of all its processes.

    .venv/bin/python benchmarks/bench_visit.py --scenario bench-out/paper-s33 \\
        --calibration bench-out/paper-s33-calibration.json --arm-workers 0 1 --json docs/results/bench_visit_s33.json

Runs the command as a user does, once per ``--arm-workers`` value (0: as many arms at once as cores, each on a
thread of the command with one core, the default; 1: the arms one after the other, each with every core), in a
fresh process each time. Every 0.2 s the
resident set (``/proc/PID/statm``) of the command and of every process below it is read: the peak of their sum
is what the machine must hold at once. The stage times are the command's own ``report.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import provenance  # noqa: E402

PAGE = os.sysconf("SC_PAGE_SIZE")


def descendants(pid: int) -> list:
    """``pid`` and every process below it (from ``/proc/*/stat``'s parent field)."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            parent[int(d.name)] = int(stat[stat.rindex(")") + 2:].split()[1])
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(c for c, pp in parent.items() if pp == p)
    return out


def resident_mb(pids) -> dict:
    """Resident set (MB) of each process still alive."""
    out = {}
    for p in pids:
        try:
            out[p] = int(Path(f"/proc/{p}/statm").read_text().split()[1]) * PAGE / 1e6
        except OSError:
            pass
    return out


def run_visit(scenario: Path, calibration: Path, capture: str, arm_workers: int, interval_s: float = 0.2) -> dict:
    """One ``torsoscan reconstruct`` of ``capture``: wall time, peak memory, and its report's figures."""
    exe = Path(sys.executable).with_name("torsoscan")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "visit"
        cmd = [str(exe), "reconstruct", "--rig", str(scenario / "rig.json"), "--calibration", str(calibration),
               "--out", str(out), "--arm-workers", str(arm_workers), str(scenario / "captures" / capture)]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        peak_all, peak_one = 0.0, 0.0
        while proc.poll() is None:
            rss = resident_mb(descendants(proc.pid))
            peak_all = max(peak_all, sum(rss.values()))
            peak_one = max(peak_one, max(rss.values(), default=0.0))
            time.sleep(interval_s)
        wall = time.perf_counter() - t0
        log = proc.stdout.read()
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{log}")
        rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    arms = {a: {k: round(v, 2) for k, v in r["seconds"].items()} for a, r in rep.get("arms", {}).items()
            if isinstance(r, dict) and "seconds" in r}
    return {"arm_workers": arm_workers, "command": " ".join(cmd[1:]).replace(str(out), "OUT"),
            "wall_s": round(wall, 1), "seconds": {k: round(v, 2) for k, v in rep["seconds"].items()},
            "arms": arms, "peak_all_processes_mb": round(peak_all), "largest_process_mb": round(peak_one),
            "points": rep.get("points"), "status": rep.get("status")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", required=True, help="a scenario folder (rig.json, captures/)")
    ap.add_argument("--calibration", required=True, help="the rig's calibration (our own, from its test field)")
    ap.add_argument("--capture", default="visit0-a")
    ap.add_argument("--arm-workers", type=int, nargs="+", default=[0])
    ap.add_argument("--repeat", type=int, default=1, help="runs of each setting (each in a fresh process)")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    res = {**provenance(__file__, argv), "scenario": args.scenario, "calibration": args.calibration,
           "capture": args.capture, "runs": []}
    for _ in range(args.repeat):
        for w in args.arm_workers:
            r = run_visit(Path(args.scenario), Path(args.calibration), args.capture, w)
            res["runs"].append(r)
            s = r["seconds"]
            print(f"arm workers {w}: {r['wall_s']:.1f} s wall (arms {s.get('arms', float('nan')):.1f}, registration "
                  f"{s.get('registration', float('nan')):.1f}, mesh {s.get('mesh', float('nan')):.1f}), peak "
                  f"{r['peak_all_processes_mb']} MB all processes, {r['largest_process_mb']} MB largest; "
                  f"{r['points']} points, {r['status']}", flush=True)
            if args.json:
                Path(args.json).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
