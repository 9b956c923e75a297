"""Where the patient's back faces, and so the patient's left and right, on bodies, builds, crops and yaws.

The facing detection (``analysis.frame.detect_posterior``) on scans of the simulator's two bodies
(MakeHuman and the parametric torso), three builds (as modelled, heavy: x1.2 / y1.4, slim: x0.9 / y0.85),
several crops of what the rig sees (the torso alone; with the neck and arms; waist to head; thighs to neck;
hips to chin) and yaws in the rig. Scans are sampled as the rig sees them (``analysis.synthetic.scan_surface``:
two cameras of an arm, 0.07 mm noise along the normal).

Two sets, never mixed:

- ``tune`` (the set the thresholds in ``analysis/frame.py`` were chosen on): straight bodies, yaws 0, 37, 123,
  211, 290 deg, sampling seeds 0-4;
- ``report`` (held out): scoliotic postures (rotation 4-14 deg at the apex, lateral 0.4 mm/deg), random yaws
  and sampling seeds drawn from ``--seed`` (default 1001), the same bodies, builds and crops.

Prints, per set: scans, wrong sides (posterior off by more than 45 deg), wrong with the status "certain" (the
defect that must never happen), "uncertain" scans, the smallest decisive midline-sagitta margin, and the old
profile-only rule's wrong sides on the same scans. ``--json FILE`` keeps every scan's figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analysis.frame import detect_posterior, facing_score, width_axis  # noqa: E402
from analysis.synthetic import scan_surface  # noqa: E402
from recon_engine.simulator.bodies import Posture, load_makehuman, make_parametric, pose_body  # noqa: E402
from recon_engine.simulator.config import SubjectConfig  # noqa: E402
from recon_engine.simulator.rig import rotation_about  # noqa: E402

BUILDS = {"modelled": (1.0, 1.0), "heavy": (1.2, 1.4), "slim": (0.9, 0.85)}


def crops(body):
    z = body.vertices[body.triangles].mean(axis=1)[:, 2]
    out = {"torso": body.torso_faces}
    if body.name == "makehuman":
        out.update({
            "neck+arms": (z > body.z_sacrum - 120) & (z < body.z_c7 + 250),
            "waist-to-head": z > body.z_sacrum + 60,
            "thighs-to-neck": (z > body.z_sacrum - 250) & (z < body.z_c7 + 100),
            "hips-to-chin": (z > body.z_sacrum - 60) & (z < body.z_c7 + 160),
        })
    return out


def old_rule(points):
    """The profile-only rule this replaced (kept here to show what it did on the same scans)."""
    w = width_axis(points)
    depth = np.cross([0.0, 0.0, 1.0], w)
    return depth if facing_score(points, depth) < facing_score(points, -depth) else -depth


def run(kind: str, seed: int, points: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    rows = []
    for body in (load_makehuman(1550.0, subdivisions=1), make_parametric(1550.0, n_around=180, n_up=130)):
        for crop, region in crops(body).items():
            for build, (sx, sy) in BUILDS.items():
                if kind == "tune":
                    cases = [(yaw, k, 0.0) for k, yaw in enumerate((0.0, 37.0, 123.0, 211.0, 290.0))]
                else:
                    cases = [(float(rng.uniform(0, 360)), int(rng.integers(1 << 30)), float(rng.uniform(4, 14)))
                             for _ in range(3)]
                for yaw, s, rot in cases:
                    R = rotation_about([0, 0, 1], yaw)
                    V, _ = pose_body(body, SubjectConfig(), Posture(rot, 0.4 * rot, 0.0, 0.0, np.eye(3), np.zeros(3)))
                    V = (V * [sx, sy, 1.0]) @ R.T
                    torso = scan_surface(V, body.triangles, region, n_points=points, seed=s)
                    truth = R @ np.array([0.0, 1.0, 0.0])
                    t0 = time.perf_counter()
                    post, info = detect_posterior(torso.points)
                    dt = time.perf_counter() - t0
                    sag = info["cues"]["midline_sagitta_mm"]
                    rows.append({"body": body.name, "crop": crop, "build": build, "yaw_deg": yaw, "seed": s,
                                 "rotation_deg": rot, "error_deg": float(np.degrees(np.arccos(np.clip(post @ truth, -1, 1)))),
                                 "status": info["status"], "sagitta_margin_mm": abs(sag["plus"] - sag["minus"]),
                                 "old_rule_error_deg": float(np.degrees(np.arccos(np.clip(old_rule(torso.points) @ truth, -1, 1)))),
                                 "seconds": dt})
    return rows


def summary(rows):
    wrong = [r for r in rows if r["error_deg"] > 45]
    return {"scans": len(rows), "wrong_sides": len(wrong),
            "wrong_and_certain": sum(r["status"] == "certain" for r in wrong),
            "uncertain": sum(r["status"] == "uncertain" for r in rows),
            "min_sagitta_margin_mm": min(r["sagitta_margin_mm"] for r in rows),
            "median_error_deg_when_right": float(np.median([r["error_deg"] for r in rows if r["error_deg"] <= 45])),
            "old_rule_wrong_sides": sum(r["old_rule_error_deg"] > 45 for r in rows),
            "seconds_median": float(np.median([r["seconds"] for r in rows]))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1001, help="the held-out set's seed")
    ap.add_argument("--points", type=int, default=40_000, help="points per scan")
    ap.add_argument("--json", help="write every scan's figures here")
    args = ap.parse_args(argv)
    out = {}
    for kind in ("tune", "report"):
        rows = run(kind, args.seed, args.points)
        out[kind] = {"summary": summary(rows), "scans": rows}
        s = out[kind]["summary"]
        print(f"{kind:6s}: {s['scans']} scans, wrong sides {s['wrong_sides']} (certain {s['wrong_and_certain']}), "
              f"uncertain {s['uncertain']}, smallest sagitta margin {s['min_sagitta_margin_mm']:.1f} mm, "
              f"median error {s['median_error_deg_when_right']:.2f} deg, old profile rule wrong on "
              f"{s['old_rule_wrong_sides']}, {1000 * s['seconds_median']:.0f} ms per scan", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
