"""Where the kyphotic angle's bias comes from: the same scans with the landmarks found and with the true ones.

    .venv/bin/python benchmarks/bench_sagittal_landmarks.py --bodies 6

The tuning bodies of ``bench_bodies.py`` (seed 100, drawn in the same order, true surfaces sampled as the rig
sees them): for each baseline scan the kyphotic and lordotic angles (``analysis.profiles.sagittal_angles``)
from ``analyse_torso`` with its own vertebra prominens and sacral point, and again with the true ones given
as a clinician's corrections, against the true skin line's angles; and the found VP's height error (mm).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from analysis.indices import analyse_torso  # noqa: E402
from bench_bodies import draw_body, scan  # noqa: E402
from recon_engine.simulator.config import preset  # noqa: E402

KEYS = ("vertebra_prominens", "sacral_point")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=100, help="bench_bodies.py's tuning seed")
    ap.add_argument("--bodies", type=int, default=6)
    ap.add_argument("--points", type=int, default=80_000)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    base = preset("paper")
    rows = []
    for b in range(args.bodies):
        draw = draw_body(rng)
        cfg = replace(base, subject=replace(base.subject, **draw["subject"]))
        subject, torso = scan(cfg, draw["rotation_deg"], draw["lateral_mm"], draw["top_mm"], rng, args.points)
        for _ in range(3):  # bench_bodies draws three more scans per body (re-scan, +5, +10): stay in step
            scan(cfg, draw["rotation_deg"], draw["lateral_mm"], draw["top_mm"], rng, 1000)
        truth = subject["true_profiles"]
        found = analyse_torso(torso).report
        given = analyse_torso(torso, landmarks={k: [float(v) for v in subject["landmarks"][k]] for k in KEYS}).report
        vp_dz = found["landmarks"]["vertebra_prominens"]["position_mm"][2] - subject["landmarks"]["vertebra_prominens"][2]
        row = [truth["kyphotic_angle_deg"], found["kyphotic_angle_deg"], given["kyphotic_angle_deg"],
               truth["lordotic_angle_deg"], found["lordotic_angle_deg"], given["lordotic_angle_deg"], vp_dz]
        rows.append(row)
        print(f"body {b}: kyphotic true {row[0]:.1f}, found landmarks {row[1]:.1f}, true landmarks {row[2]:.1f}; "
              f"lordotic {row[3]:.1f} / {row[4]:.1f} / {row[5]:.1f}; found VP {vp_dz:+.1f} mm in height", flush=True)
    r = np.array(rows, dtype=float)
    print(f"kyphotic error, mean (min, max): found landmarks {np.mean(r[:, 1] - r[:, 0]):+.2f} "
          f"({np.min(r[:, 1] - r[:, 0]):+.2f}, {np.max(r[:, 1] - r[:, 0]):+.2f}) deg; true landmarks "
          f"{np.mean(r[:, 2] - r[:, 0]):+.2f} ({np.min(r[:, 2] - r[:, 0]):+.2f}, {np.max(r[:, 2] - r[:, 0]):+.2f}) deg")
    print(f"lordotic error, mean: found {np.mean(r[:, 4] - r[:, 3]):+.2f}, true landmarks {np.mean(r[:, 5] - r[:, 3]):+.2f} deg; "
          f"found VP height error mean {np.mean(r[:, 6]):+.1f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
