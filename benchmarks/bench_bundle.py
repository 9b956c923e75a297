"""Benchmark: time of the calibration's bundle adjustments (issue 29), pass by pass.

    .venv/bin/python benchmarks/bench_bundle.py --scenario bench-out/tiny-tf [--poses 0,1] [--engine DIR]

Calibrates the scenario's test-field captures (``--poses``: only those) and
prints the wall and CPU time of the whole calibration and of each bundle
adjustment, with its size and outcome. A missing ``--scenario`` is simulated
first: the tiny preset's test field as the tests' ``rig_session_1`` (seed 11,
session 1). ``--engine DIR`` times another version of the engine, e.g. the
dense solver: ``git archive b61c93c recon_engine | tar -x -C /tmp/old`` then
``--engine /tmp/old``. Set ``OPENBLAS_NUM_THREADS=1`` on a shared machine:
threaded BLAS on busy cores makes even small solves slow and the timings
meaningless. ``--json OUT`` writes the figures with the run's provenance.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bench-out/tiny-tf")
    ap.add_argument("--poses", help="comma-separated test-field poses to use (default: all)")
    ap.add_argument("--engine", help="folder holding the recon_engine package to time (default: this checkout's)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    sys.path.insert(0, args.engine or str(Path(__file__).resolve().parents[1]))
    sys.path.insert(1, str(Path(__file__).resolve().parent))
    from recon_engine import bundle
    from recon_engine.calibration import calibrate
    from recon_engine.formats import read_capture, read_rig, read_testfield

    from provenance import provenance

    run = provenance(__file__)

    scenario = Path(args.scenario)
    if not (scenario / "rig.json").exists():
        from recon_engine.simulator.config import preset
        from recon_engine.simulator.scenario import simulate

        t0 = time.perf_counter()
        simulate(scenario, preset("tiny", seed=11, captures=(), session=1), progress=lambda m: None)
        print(f"simulated {scenario} in {time.perf_counter() - t0:.0f} s")
    rig = read_rig(scenario / "rig.json")
    tf = read_testfield(scenario / "testfield.json")
    caps = [read_capture(p, rig) for p in sorted((scenario / "captures").glob("testfield-pose*"))]
    if args.poses:
        wanted = {int(p) for p in args.poses.split(",")}
        caps = [c for c in caps if c.pose in wanted]
    passes = []
    adjust = bundle.adjust

    def timed(pb, **kw):
        t0, c0 = time.perf_counter(), time.process_time()
        sol = adjust(pb, **kw)
        passes.append((time.perf_counter() - t0, time.process_time() - c0, pb, sol))
        return sol

    bundle.adjust = timed
    t0, c0 = time.perf_counter(), time.process_time()
    calibrate(caps, rig, tf)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"Machine: {run['machine']}; engine {Path(bundle.__file__).parents[1]}")
    print(f"{len(rig.camera_ids)} cameras, poses {[c.pose for c in caps]}: calibration {wall:.1f} s wall, "
          f"{cpu:.1f} s CPU, peak RSS {peak:.0f} MiB")
    for i, (w, c, pb, sol) in enumerate(passes, 1):
        print(f"  adjustment pass {i}: {w:.2f} s wall, {c:.2f} s CPU; {len(pb.uv)} corners observed, "
              f"{len(pb.points)} corners, {sol.iterations} iterations, sigma0 {sol.sigma0:.6f}, "
              f"converged {sol.converged} {getattr(sol, 'reason', '')}")
    print(f"  adjustments together: {sum(p[0] for p in passes):.2f} s wall, {sum(p[1] for p in passes):.2f} s CPU")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({
            **run, "engine": str(Path(bundle.__file__).parents[1]), "scenario": str(scenario),
            "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "cameras": len(rig.camera_ids),
            "poses": [c.pose for c in caps], "calibration_wall_s": wall, "calibration_cpu_s": cpu,
            "peak_rss_mib": peak,
            "passes": [{"wall_s": w, "cpu_s": c, "observations": len(pb.uv), "corners": len(pb.points),
                        "iterations": sol.iterations,
                        "sigma0": float(sol.sigma0), "converged": bool(sol.converged)}
                       for w, c, pb, sol in passes]}, indent=2))
        print(f"raw figures: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
