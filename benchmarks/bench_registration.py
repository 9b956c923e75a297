"""Benchmark: registration alone, on arm surfaces kept by ``bench_reconstruct.py --keep-surfaces``.

    .venv/bin/python benchmarks/bench_reconstruct.py --capture visit0-a visit0-b visit1-a --keep-surfaces
    .venv/bin/python benchmarks/bench_registration.py --capture visit0-a visit0-b visit1-a

The same four surfaces of each capture are registered by our ICPatch (the
default configuration and the variants below) and by Open3D's pair-wise ICP
and multiway registration, and each arm's recovered displacement is compared
with the simulator's truth: the RMS position error over the torso's true
surface (mm) and the rotation error (deg). Reconstruction is not repeated, so
registration settings can be compared in seconds on exactly the same data.
Writes ``bench-out/bench_registration.json``.
"""

from __future__ import annotations

import argparse
import json
import pickle
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from recon_engine.formats import read_calibration, read_rig  # noqa: E402
from recon_engine.reconstruction import TorsoConfig, register_arms  # noqa: E402
from recon_engine.registration import ICPatchConfig, Transform  # noqa: E402

from bench_reconstruct import displacement_errors, open3d_multiway, open3d_pairwise  # noqa: E402
from bench_reconstruct_arm import Truth  # noqa: E402
from bench_simulate import machine  # noqa: E402

# our registration's variants: name -> changes to the default ICPatchConfig
VARIANTS = {
    "ours": {},
    "ours_weighted": {"weighted": True},
    "ours_rigid": {"estimate_scale": False},
    "ours_weighted_rigid": {"weighted": True, "estimate_scale": False},
    "ours_scale_sigma_1e-4": {"scale_sigma": 1e-4},
    "ours_scale_sigma_2e-5": {"scale_sigma": 2e-5},
    "ours_weighted_scale_sigma_2e-5": {"weighted": True, "scale_sigma": 2e-5},
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bench-out/paper")
    ap.add_argument("--capture", nargs="+", default=["visit0-a", "visit0-b", "visit1-a"])
    ap.add_argument("--calibration", default="bench-out/paper-calibration.json")
    ap.add_argument("--variant", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    args = ap.parse_args()
    S = Path(args.scenario)
    rig = read_rig(S / "rig.json")
    cal = read_calibration(args.calibration)
    base = TorsoConfig().icpatch
    rows = {}
    for capture in args.capture:
        with open(f"bench-out/surfaces-{capture}.pkl", "rb") as f:
            kept = pickle.load(f)
        surfaces, reports, failed = kept["surfaces"], kept["reports"], kept["failed"]
        truth = Truth(S, capture)
        disp = json.loads((S / "truth" / capture / "truth.json").read_text())["arm_displacements"]
        D = {a: Transform(1.0, np.array(v["R"]), np.array(v["t"])) for a, v in disp.items()}
        order = [a.id for a in rig.arms if a.id in surfaces]
        runs = {}
        for name in args.variant:
            icfg = replace(base, **VARIANTS[name])
            t0 = time.perf_counter()
            res = register_arms(surfaces, reports, failed, rig, cal, TorsoConfig(icpatch=icfg))
            runs[name] = {"errors": displacement_errors(res["transforms"], D, truth.centroid),
                          "seconds": res["report"]["seconds"]["registration"], "status": res["report"]["status"],
                          "table1": [(p["a"], p["b"], p["average_normal_distance_mm"])
                                     for p in res["report"]["registration"]["pairs"]]}
            del t0
        for name, fn in (("open3d_icp_pairwise", open3d_pairwise), ("open3d_multiway", open3d_multiway)):
            t0 = time.perf_counter()
            T = fn(surfaces, order)
            runs[name] = {"errors": displacement_errors(T, D, truth.centroid), "seconds": time.perf_counter() - t0}
        for name, r in runs.items():
            errs = {a: round(e["rms_mm"], 4) for a, e in r["errors"].items() if a != rig.reference_arm.id}
            print(f"{capture} {name:24s} {errs} {r['seconds']:.1f} s", flush=True)
        rows[capture] = runs
    summary = {}
    for name in next(iter(rows.values())):
        e = [v for runs in rows.values() for a, v in runs[name]["errors"].items() if a != rig.reference_arm.id]
        summary[name] = {"arms": len(e), "mean_rms_mm": float(np.mean([x["rms_mm"] for x in e])),
                         "max_rms_mm": float(np.max([x["rms_mm"] for x in e])),
                         "mean_rotation_deg": float(np.mean([x["rotation_deg"] for x in e])),
                         "seconds_mean": float(np.mean([runs[name]["seconds"] for runs in rows.values()]))}
        print(f"{name:24s} mean {summary[name]['mean_rms_mm']:.4f} mm, max {summary[name]['max_rms_mm']:.4f} mm, "
              f"{summary[name]['mean_rotation_deg']:.4f} deg, {summary[name]['seconds_mean']:.1f} s")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    Path("bench-out/bench_registration.json").write_text(json.dumps(
        {"machine": machine(), "commit": commit, "command": " ".join(["benchmarks/bench_registration.py", *sys.argv[1:]]),
         "captures": rows, "summary": summary}, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
