"""Benchmark: row agreement of epipolar resampling over true correspondences, true and own calibration.

    .venv/bin/python benchmarks/bench_epipolar.py --scenario bench-out/paper --capture visit0-a \
        --calibration bench-out/paper-calibration.json

True torso points that both cameras of a neighbouring pair see (unoccluded)
are projected with the true cameras at capture time; their images are
rectified with the true calibration and with ours. Arm A only, for our own
calibration: it does not move between calibration and capture. Prints the
median and 95th percentile of the row difference (px) per pair, and writes them
with the run's provenance to ``--json`` (default ``bench-out/bench_epipolar.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from recon_engine.epipolar import rectify_pair  # noqa: E402
from recon_engine.formats import read_calibration, read_rig  # noqa: E402

from bench_reconstruct_arm import Truth  # noqa: E402
from provenance import provenance  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bench-out/paper")
    ap.add_argument("--capture", default="visit0-a")
    ap.add_argument("--calibration", default="bench-out/paper-calibration.json")
    ap.add_argument("--json", default="bench-out/bench_epipolar.json", help="where to write the figures")
    args = ap.parse_args()
    run = provenance(__file__)
    S = Path(args.scenario)
    rig = read_rig(S / "rig.json")
    true_cal = read_calibration(S / "truth" / args.capture / "calibration.json")
    own = read_calibration(args.calibration) if Path(args.calibration).exists() else None
    truth = Truth(S, args.capture)
    print(f"Machine: {run['machine']}\n")
    rows = []
    print("| pair | calibration | points | median row difference (px) | 95th percentile (px) |")
    print("|---|---|---|---|---|")
    for arm in rig.arms:
        for a, b in zip(arm.cameras[:-1], arm.cameras[1:]):
            ca, cb = true_cal.cameras[a], true_cal.cameras[b]
            both = truth.seen(ca) & truth.seen(cb)
            X = truth.centroid[both]
            ua, ub = ca.project(X), cb.project(X)
            cals = [("true", true_cal)] + ([("ours", own)] if own is not None and arm.id == rig.reference_arm.id else [])
            for name, cal in cals:
                p = rectify_pair(cal.cameras[a], cal.cameras[b])
                d = np.abs(p.to_rectified("left", ua)[:, 1] - p.to_rectified("right", ub)[:, 1])
                rows.append({"pair": f"{a}-{b}", "arm": arm.id, "calibration": name, "points": int(len(d)),
                             "median_px": float(np.median(d)), "p95_px": float(np.percentile(d, 95))})
                print(f"| {a}-{b} | {name} | {len(d)} | {np.median(d):.4f} | {np.percentile(d, 95):.4f} |")
    dest = Path(args.json)
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps({**run, "scenario": str(S), "capture": args.capture,
                                "calibration_ours": args.calibration if own is not None else None,
                                "pairs": rows}, indent=2))
    print(f"raw figures: {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
