"""Benchmark: the whole torso end to end at paper scale (our calibration, arms displaced).

    .venv/bin/python benchmarks/bench_reconstruct.py --scenario bench-out/paper --capture visit0-a \
        --calibration bench-out/paper-calibration.json

``--calibration`` is our own calibration from the scenario's raw test-field
images (``bench_calibrate.py`` or ``torsoscan calibrate`` writes it). The
torso capture's arms B, C, D are displaced from their calibrated placement;
ICPatch brings them back. Figures: distance of the fused torso points to the
true body (RMS, 95th percentile, max), coverage of the torso area that two
cameras of one arm see, the paper's Table 1 (average normal distance and
matched fraction of every neighbouring pair after the multiple
registration), the misclosure that pair-wise registration alone leaves at the
closing pair, and the time of each stage. Writes
``bench-out/bench_reconstruct.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from recon_engine.formats import read_calibration, read_capture, read_rig  # noqa: E402
from recon_engine.reconstruction import reconstruct_torso  # noqa: E402

from bench_reconstruct_arm import Truth  # noqa: E402
from bench_simulate import machine  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bench-out/paper")
    ap.add_argument("--capture", default="visit0-a")
    ap.add_argument("--calibration", default="bench-out/paper-calibration.json")
    args = ap.parse_args()
    S = Path(args.scenario)
    rig = read_rig(S / "rig.json")
    cal = read_calibration(args.calibration)
    cap = read_capture(S / "captures" / args.capture, rig)
    t0 = time.perf_counter()
    res = reconstruct_torso(cap, rig, cal, progress=lambda m: print(f"  {m}", flush=True))
    wall = time.perf_counter() - t0
    truth = Truth(S, args.capture)
    true_cal = read_calibration(S / "truth" / args.capture / "calibration.json")
    P = res["points"]
    d = truth.distance(P)
    # torso area that two cameras of one arm see (matching happens inside an arm)
    seen2 = np.zeros(len(truth.area), bool)
    for arm in rig.arms:
        seen = np.sum([truth.seen(true_cal.cameras[c]) for c in arm.cameras], axis=0)
        seen2 |= seen >= 2
    near, _ = cKDTree(P).query(truth.centroid[seen2], k=1, distance_upper_bound=2.0)
    covered = np.isfinite(near)
    coverage = float(truth.area[seen2][covered].sum() / truth.area[seen2].sum())
    rep = res["report"]
    reg = rep["registration"]
    out = {
        "machine": machine(),
        "command": " ".join(["benchmarks/bench_reconstruct.py", *sys.argv[1:]]),
        "points": int(len(P)), "rms_mm": float(np.sqrt(np.mean(d ** 2))), "p95_mm": float(np.percentile(d, 95)),
        "max_mm": float(d.max()), "coverage": coverage, "seen_area_cm2": float(truth.area[seen2].sum() / 100),
        "table1": reg["pairs"], "pairwise": reg["pairwise"], "sigmas": reg["sigmas"],
        "closing_pair_after_pairwise_only": reg["closing_pair_after_pairwise_only"],
        "seconds": {**rep["seconds"], "wall": wall},
        "arm_seconds": {a: r["seconds"]["total"] for a, r in rep["arms"].items()},
    }
    Path("bench-out/bench_reconstruct.json").write_text(json.dumps(out, indent=2))
    print(json.dumps({k: v for k, v in out.items() if k not in ("pairwise", "sigmas")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
