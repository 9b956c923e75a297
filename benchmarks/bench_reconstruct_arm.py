"""Benchmark: one arm's reconstruction at paper scale, against the truth and two peers.

    .venv/bin/python benchmarks/bench_reconstruct_arm.py --scenario bench-out/paper --capture visit0-a

For every arm of the capture, with our own calibration of the rig
(``--calibration``, made by ``torsoscan calibrate`` from the scenario's
test-field captures; ``--true-calibration`` for the capture-time truth
instead): the points of every method are reconstructed in the calibration's
frame and moved by the arm's true displacement since the calibration (the
torso's registration estimates it; this benchmark is about one arm).

- ours: ``reconstruction.reconstruct_arm``;
- OpenCV's StereoSGBM on the same rectified neighbouring pairs (tuned: 3-way
  mode, block 5, P1/P2 = 8/32·block², left-right check ``disp12MaxDiff=1``,
  uniqueness 10, speckle filter), every second pixel of our region of
  interest triangulated from its two rays, then our own surface filters
  (``surface_from_intersection``: our ray test, precision, off the local
  surface, islands); the unfiltered points are reported too;
- pycolmap (``peer_pycolmap.py``): dense SIFT, matching of the same
  neighbouring pairs, ``triangulate_points`` with the known poses; points of
  tracks of three or more images (those of two-view tracks too, apart).

Figures: distance of the points to the true body surface (RMS, 95th
percentile, max), coverage (share of the torso area that two or more of the
arm's cameras see with a point within 2 mm), density (points per cm² of that
area) and wall time. Writes ``bench-out/bench_reconstruct_arm.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from recon_engine.o3d import o3d  # noqa: E402

from recon_engine.epipolar import rectify_pair, rig_centre, subject_depth_bounds  # noqa: E402
from recon_engine.features import region_of_interest  # noqa: E402
from recon_engine.formats import load_image, read_calibration, read_capture, read_rig  # noqa: E402
from recon_engine.multiview import IntersectionConfig, intersect  # noqa: E402
from recon_engine.parallel import reuse_freed_images  # noqa: E402
from recon_engine.reconstruction import (ReconstructionConfig, arm_cameras, reconstruct_arm,  # noqa: E402
                                         refine_on_local_quadrics, surface_from_intersection)

from provenance import provenance  # noqa: E402


class Truth:
    """The posed body (distances) and the torso's triangles with what each arm's cameras see."""

    def __init__(self, scenario: Path, capture: str):
        body = o3d.io.read_triangle_mesh(str(scenario / "truth" / capture / "body.ply"))
        torso = o3d.io.read_triangle_mesh(str(scenario / "truth" / capture / "torso.ply"))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(body))
        V, F = np.asarray(torso.vertices), np.asarray(torso.triangles)
        a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        n = np.cross(b - a, c - a)
        self.area = 0.5 * np.linalg.norm(n, axis=1)
        self.normal = n / np.maximum(2 * self.area[:, None], 1e-12)
        self.centroid = (a + b + c) / 3

    def distance(self, points):
        return self.scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()

    def seen(self, cam) -> np.ndarray:
        P, N = self.centroid, self.normal
        to = cam.C - P
        dist = np.linalg.norm(to, axis=1)
        facing = np.abs(np.sum(to / dist[:, None] * N, axis=1)) > 0.1
        uv = cam.project(P)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        # unoccluded: the ray from the camera reaches the point (lifted clear of its own triangle)
        lifted = P + 0.5 * N * np.sign(np.sum(to * N, axis=1))[:, None]
        d = lifted - cam.C
        L = np.linalg.norm(d, axis=1)
        rays = np.column_stack([np.repeat(cam.C[None], len(P), 0), d / L[:, None]]).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        return facing & inside & (hit >= L - 1.0)

    def figures(self, points, cams) -> dict:
        points = np.asarray(points, float).reshape(-1, 3)
        if len(points) == 0:
            return {"points": 0}
        d = self.distance(points)
        seen = np.array([self.seen(c) for c in cams])
        seen2 = seen.sum(axis=0) >= 2
        area_cm2 = self.area[seen2].sum() / 100.0
        near, _ = cKDTree(points).query(self.centroid[seen2], k=1, distance_upper_bound=2.0)
        covered = np.isfinite(near)
        # the same, only where two cameras see the skin within 60 deg of its normal
        cos = np.array([np.abs(np.sum((c.C - self.centroid) / np.linalg.norm(c.C - self.centroid, axis=1)[:, None]
                                      * self.normal, axis=1)) for c in cams])
        second = np.sort(np.where(seen, cos, 0), axis=0)[-2][seen2]
        frontal = second >= 0.5
        # density over the seen torso: points that lie on it (within 2 mm of a seen triangle's centroid region)
        on_torso, _ = cKDTree(self.centroid[seen2]).query(points, k=1, distance_upper_bound=3.0)
        return {"points": int(len(points)), "rms_mm": float(np.sqrt(np.mean(d ** 2))),
                "p95_mm": float(np.percentile(d, 95)), "max_mm": float(d.max()),
                "beyond_2mm": int((d > 2).sum()),
                "coverage": float(self.area[seen2][covered].sum() / max(self.area[seen2].sum(), 1e-9)),
                "coverage_within_60deg": float(self.area[seen2][covered & frontal].sum()
                                               / max(self.area[seen2][frontal].sum(), 1e-9)),
                "area_beyond_60deg_fraction": float(self.area[seen2][~frontal].sum() / max(self.area[seen2].sum(), 1e-9)),
                "seen_area_cm2": float(area_cm2),
                "density_per_cm2": float(np.isfinite(on_torso).sum() / max(area_cm2, 1e-9))}


def sgbm_arm(images, cams, centre, radius_mm=400.0, step=2, block=5, filters: ReconstructionConfig | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """StereoSGBM on each neighbouring rectified pair, triangulated; ``(points, filtered, refined, seconds)``.

    ``filtered``: the same points after our own surface filters (``surface_from_intersection`` with our
    intersection's ray test: imprecise points, points off the local surface, islands), pair by pair;
    ``refined``: those after our refinement on local quadrics too (``refine_on_local_quadrics``, its window bias
    for SGBM's own block of ``block`` px). ``seconds`` is SGBM with the filters, the refinement left out.
    """
    filters = filters or ReconstructionConfig()
    block_cfg = replace(filters, tracking=replace(filters.tracking, matching=replace(
        filters.tracking.matching, lsm_window=block)))
    t0 = time.perf_counter()
    refine_s = 0.0
    pts, kept, refined = [], [], []
    for k in range(len(images) - 1):
        pair = rectify_pair(cams[k], cams[k + 1])
        L = pair.resample("left", images[k])
        R = pair.resample("right", images[k + 1])
        roi = region_of_interest(L.astype(np.float32))
        d0, d1 = pair.disparity_range(*subject_depth_bounds(pair, centre, radius_mm))
        dmin = int(np.floor(d0))
        ndisp = int(np.ceil((d1 - dmin) / 16.0)) * 16
        # a competent user crops to the rows where the subject is
        rows = np.nonzero(roi.any(axis=1))[0]
        r0, r1 = max(rows.min() - 8, 0), min(rows.max() + 9, L.shape[0])
        sgbm = cv2.StereoSGBM_create(minDisparity=dmin, numDisparities=ndisp, blockSize=block,
                                     P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
                                     uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                     preFilterCap=63, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
        disp = sgbm.compute(L[r0:r1], R[r0:r1]).astype(np.float32) / 16.0
        yy, xx = np.mgrid[r0:r1:step, 0:L.shape[1]:step]
        dd = disp[yy - r0, xx]
        ok = roi[yy, xx] & (dd >= dmin)
        xl = np.column_stack([xx[ok], yy[ok]]).astype(float)
        xr = xl - np.column_stack([dd[ok], np.zeros(ok.sum())])
        obs = np.stack([pair.to_original("left", xl), pair.to_original("right", xr)], axis=1)
        two = [cams[k], cams[k + 1]]
        res = intersect(two, obs, IntersectionConfig(chi2_ray=1e12, min_angle_deg=0))
        pts.append(res["X"][res["valid"]])
        surface, _, _ = surface_from_intersection(intersect(two, obs, filters.intersection), two, filters)
        kept.append(surface.points)
        t1 = time.perf_counter()
        refined.append(refine_on_local_quadrics(surface, two, block_cfg)[0].points)
        refine_s += time.perf_counter() - t1
    return (np.concatenate(pts), np.concatenate(kept), np.concatenate(refined),
            time.perf_counter() - t0 - refine_s)


def arm_displacement(scenario: Path, capture: str, arm: str):
    """``(R, t)``: how the arm was moved between the calibration and the capture (world frame, mm):
    ``X_displaced = R @ X_calibrated + t``; the identity when the truth does not say."""
    truth = json.loads((scenario / "truth" / capture / "truth.json").read_text())
    d = (truth.get("arm_displacements") or {}).get(arm)
    if d is None:
        return np.eye(3), np.zeros(3)
    return np.asarray(d["R"], float), np.asarray(d["t"], float)


def measure_arm(cap, rig, cal, arm: str, truth: Truth, seen_by: list, placed=lambda p: p, cfg=None, *,
                centre=None, peers=frozenset({"sgbm", "pycolmap"}), ours: bool = True,
                pycolmap_work: Path = Path("bench-out/pycolmap")) -> dict:
    """One arm of one capture, by ours and the ``peers``, against the truth: the benchmark's row.

    ``cal`` is the calibration every method is given; ``seen_by`` the arm's
    cameras at capture time (what decides the area two of them saw);
    ``placed`` moves points from the calibration's frame into the capture's
    (mm). Each method's figures, with its time (s); SGBM with our filters;
    pycolmap's points with tracks of 3 images or more (and, for reference,
    with two-image tracks too), its work folder made afresh.
    """
    ids = arm_cameras(rig, arm)
    cams = [cal.cameras[c] for c in ids]
    centre = rig_centre(list(cal.cameras.values())) if centre is None else centre
    row = {}
    if ours:
        t0 = time.perf_counter()
        surface, report = reconstruct_arm(cap, rig, cal, arm, cfg)
        row["ours"] = {**truth.figures(placed(surface.points), seen_by), "seconds": time.perf_counter() - t0,
                       "rays_per_point": report["rays_per_point"]}
    images = [load_image(cap, c, rig) for c in ids]
    if "sgbm" in peers:
        raw, filtered, refined, t_sg = sgbm_arm(images, cams, centre)
        row["sgbm"] = {**truth.figures(placed(filtered), seen_by), "seconds": t_sg,
                       "filters": "ours (precision, off the local surface, islands)"}
        row["sgbm_unfiltered"] = truth.figures(placed(raw), seen_by)
        # the peer with our refinement on local quadrics too (its own block's window bias): the stage is ours,
        # but a competent user of SGBM could smooth its points so
        row["sgbm_refined"] = {**truth.figures(placed(refined), seen_by),
                               "filters": "ours, then our refinement on local quadrics (5 px window)"}
    if "pycolmap" in peers:
        from peer_pycolmap import pycolmap_arm

        if pycolmap_work.exists():
            shutil.rmtree(pycolmap_work)  # a database left by an earlier run would be read, not made again
        t0 = time.perf_counter()
        pc = pycolmap_arm(images, cams, pycolmap_work)
        three = pc["track_lengths"] >= 3
        row["pycolmap"] = {**truth.figures(placed(pc["points"][three]), seen_by),
                           "seconds": time.perf_counter() - t0, "tracks": ">= 3 images"}
        row["pycolmap_two_view_tracks_too"] = truth.figures(placed(pc["points"]), seen_by)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bench-out/paper")
    ap.add_argument("--capture", default="visit0-a")
    ap.add_argument("--calibration", default="bench-out/paper-calibration.json",
                    help="our own calibration of the rig, from its test-field captures (every arm is reconstructed "
                         "with it; its points are then moved by the arm's true displacement since the calibration, "
                         "which the torso's registration estimates)")
    ap.add_argument("--true-calibration", action="store_true",
                    help="use the capture-time true calibration instead (say so in the table's header)")
    ap.add_argument("--arms", default="A,B,C,D")
    ap.add_argument("--pycolmap-arms", default="A", help="arms pycolmap runs on (about 100 s per arm)")
    ap.add_argument("--no-pycolmap", action="store_true")
    ap.add_argument("--no-sgbm", action="store_true", help="ours (and pycolmap) only")
    ap.add_argument("--fill-spacing-mm", type=float, default=None,
                    help="our TrackingConfig.fill_spacing_mm (a cheaper rig: 2.0; default: the engine's)")
    ap.add_argument("--max-sigma-factor", type=float, default=None,
                    help="our ReconstructionConfig.max_sigma_factor (with the fill: 4.0; default: the engine's)")
    ap.add_argument("--json", default="bench-out/bench_reconstruct_arm.json")
    args = ap.parse_args()
    ours_cfg = ReconstructionConfig()
    if args.fill_spacing_mm is not None:
        ours_cfg = replace(ours_cfg, tracking=replace(ours_cfg.tracking, fill_spacing_mm=args.fill_spacing_mm))
    if args.max_sigma_factor is not None:
        ours_cfg = replace(ours_cfg, max_sigma_factor=args.max_sigma_factor)
    reuse_freed_images()  # as the command line does: the figures are the CLI's
    S = Path(args.scenario)
    rig = read_rig(S / "rig.json")
    truth_cal = read_calibration(S / "truth" / args.capture / "calibration.json")
    if args.true_calibration:
        cal = truth_cal
    elif Path(args.calibration).exists():
        cal = read_calibration(args.calibration)
    else:
        ap.error(f"--calibration {args.calibration}: no such file (make it with `torsoscan calibrate`, "
                 "or pass --true-calibration)")
    cap = read_capture(S / "captures" / args.capture, rig)
    truth = Truth(S, args.capture)
    centre = rig_centre(list(cal.cameras.values()))
    out = {**provenance(__file__),
           "calibration": "true, capture time" if args.true_calibration else f"ours: {args.calibration}",
           "ours_settings": {"fill_spacing_mm": ours_cfg.tracking.fill_spacing_mm,
                             "max_sigma_factor": ours_cfg.max_sigma_factor},
           "arms": {}}
    total_ours = 0.0
    for arm in args.arms.split(","):
        seen_by = [truth_cal.cameras[c] for c in arm_cameras(rig, arm)]  # the arm's cameras at capture time
        R, t = (np.eye(3), np.zeros(3)) if args.true_calibration else arm_displacement(S, args.capture, arm)

        def placed(points):  # the calibration's frame -> the capture's (the arm moved since)
            return np.asarray(points, float).reshape(-1, 3) @ R.T + t

        peers = {"sgbm"} if not args.no_sgbm else set()
        if not args.no_pycolmap and arm in args.pycolmap_arms.split(","):
            peers.add("pycolmap")
        row = measure_arm(cap, rig, cal, arm, truth, seen_by, placed, ours_cfg, centre=centre, peers=peers,
                          pycolmap_work=Path("bench-out") / f"pycolmap-{arm}")
        total_ours += row["ours"]["seconds"]
        out["arms"][arm] = row
        print(arm, json.dumps({k: {kk: (round(vv, 4) if isinstance(vv, float) else vv) for kk, vv in v.items()
                                   if kk != "rays_per_point"} for k, v in row.items()}), flush=True)
    out["four_arms_seconds_ours"] = total_ours
    dest = Path(args.json)
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(out, indent=2))
    print(f"raw figures: {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
