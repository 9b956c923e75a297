"""Checks of the simulator's faithfulness against its own truth.

Used by the tests (tiny preset) and the benchmark (paper scale):

- marker corners measured in the rendered test-field images, with a method
  independent of OpenCV's corner refinement (edges fitted in the undistorted
  image), against the truth projection of the true corners through the true
  lens (:mod:`.lens`, with the terms the engine's model lacks);
- normalized cross-correlation of patches around truth-projected torso points
  between neighbouring cameras of an arm.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from ..camera import Camera
from ..formats import load_images, read_calibration, read_capture, read_rig, read_testfield
from ..imaging import sample_bilinear
from ..targets import detect_markers, measure_markers
from . import lens as sim_lens
from .render import Scene, Surface


def _project(cam: Camera, lens, X) -> np.ndarray:
    """Pixels of world points through the true lens (not the engine's model)."""
    return sim_lens.project(lens, cam.R, cam.C, X)


def marker_corner_errors(scenario: str | Path) -> dict:
    """Distances (px) between measured and true marker corners, all test-field images.

    Returns ``{"edge_fit": (N,), "opencv_subpix": (N,)}``: our edge-fitted
    corners, and OpenCV's ``cornerSubPix`` from the same detections for
    comparison.
    """
    out = Path(scenario)
    rig = read_rig(out / "rig.json")
    cal = read_calibration(out / "truth" / "calibration.json")
    lenses = sim_lens.true_lenses(cal)
    true_tf = read_testfield(out / "truth" / "testfield.json")
    poses = json.loads((out / "truth" / "testfield_poses.json").read_text())["poses"]
    ours, theirs = [], []
    for pose in poses:
        R, t = np.array(pose["R"]), np.array(pose["t"])
        cap = read_capture(out / "captures" / f"testfield-pose{pose['pose']}", rig)
        for cam_id, image in load_images(cap, rig).items():
            cam = cal.cameras[cam_id]
            ids, corners, _ = measure_markers(image, true_tf.aruco_dictionary, cam)
            known = np.array([i in true_tf.markers for i in ids], dtype=bool)
            if not known.any():
                continue
            X = np.array([true_tf.markers[i] for i in ids[known]]).reshape(-1, 3) @ R.T + t
            truth = _project(cam, lenses[cam_id], X).reshape(-1, 4, 2)
            ours.append(np.linalg.norm(corners[known] - truth, axis=-1).ravel())
            ids_cv, coarse = detect_markers(image, true_tf.aruco_dictionary)
            keep = np.array([i in true_tf.markers for i in ids_cv], dtype=bool)
            if keep.any():
                pts = coarse[keep].reshape(-1, 1, 2).astype(np.float32)
                crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
                win = max(2, int(0.05 * np.linalg.norm(coarse[0, 0] - coarse[0, 1])))
                cv2.cornerSubPix(image, pts, (win, win), (-1, -1), crit)
                X = np.array([true_tf.markers[i] for i in ids_cv[keep]]).reshape(-1, 3) @ R.T + t
                theirs.append(np.linalg.norm(pts.reshape(-1, 2) - _project(cam, lenses[cam_id], X), axis=-1))
    return {"edge_fit": np.concatenate(ours) if ours else np.zeros(0),
            "opencv_subpix": np.concatenate(theirs) if theirs else np.zeros(0)}


def neighbour_ncc(scenario: str | Path, capture: str, half: int | None = None,
                  max_points: int = 4000, min_cosine: float = 0.5) -> dict:
    """Median NCC of patches around true torso points, per neighbouring camera pair.

    Points are the centroids of the true torso mesh's triangles that both
    cameras see unoccluded and at most ``acos(min_cosine)`` off the surface
    normal. Patches are ``(2 * half + 1)²`` pixels of the first camera
    (default: 4 px at 480 px wide, scaled with the image width), sampled
    bilinearly; the second camera's patch samples the same piece of skin
    (the first patch's pixels carried through the surface's tangent plane).
    Returns ``{"A1-A2": median, ...}``.
    """
    from ..o3d import o3d

    out = Path(scenario)
    rig = read_rig(out / "rig.json")
    cal = read_calibration(out / "truth" / capture / "calibration.json")
    lenses = sim_lens.true_lenses(cal)
    images = load_images(read_capture(out / "captures" / capture, rig), rig)
    body = o3d.io.read_triangle_mesh(str(out / "truth" / capture / "body.ply"))
    torso = o3d.io.read_triangle_mesh(str(out / "truth" / capture / "torso.ply"))
    torso.compute_triangle_normals()
    scene = Scene([Surface("skin", np.asarray(body.vertices), np.asarray(body.triangles),
                           albedo=np.ones(len(body.vertices)))])
    V, tri = np.asarray(torso.vertices), np.asarray(torso.triangles)
    P = V[tri].mean(axis=1)
    N = np.asarray(torso.triangle_normals)
    pick = np.random.default_rng(0).permutation(len(P))
    P, N = P[pick], N[pick]
    result = {}
    for arm in rig.arms:
        for a, b in zip(arm.cameras[:-1], arm.cameras[1:]):
            if a not in images or b not in images:
                continue
            ca, cb = cal.cameras[a], cal.cameras[b]
            h = half if half is not None else max(4, round(4 * ca.width / 480))
            sel = np.ones(len(P), dtype=bool)
            for cam in (ca, cb):
                d = cam.C - P
                sel &= np.einsum("ij,ij->i", d / np.linalg.norm(d, axis=1, keepdims=True), N) > min_cosine
            idx = np.flatnonzero(sel)[: 3 * max_points]
            lifted = P[idx] + 0.2 * N[idx]  # clear of the surface itself
            idx = idx[scene.visible(ca.C, lifted) & scene.visible(cb.C, lifted)][:max_points]
            ua, ub = _project(ca, lenses[a], P[idx]), _project(cb, lenses[b], P[idx])
            inside = np.all((ua > h + 1) & (ua < [ca.width - h - 2, ca.height - h - 2]), axis=1)
            inside &= np.all((ub > h + 1) & (ub < [cb.width - h - 2, cb.height - h - 2]), axis=1)
            ua, ub = ua[inside], ub[inside]
            if len(ua) < 20:
                continue
            g = np.arange(-h, h + 1)
            gx, gy = np.meshgrid(g, g)
            pa = sample_bilinear(images[a], ua[:, :1] + gx.ravel(), ua[:, 1:] + gy.ravel()).astype(float)
            # the same piece of skin in b: a's patch pixels through the tangent plane into b
            # (a square in b would compare different skin wherever the views foreshorten differently)
            Pk, Nk = P[idx][inside], N[idx][inside]
            grid_a = np.stack([ua[:, :1] + gx.ravel(), ua[:, 1:] + gy.ravel()], axis=2).reshape(-1, 2)
            rays = sim_lens.rays(lenses[a], ca.R, grid_a).reshape(len(ua), -1, 3)
            t = np.einsum("ij,ij->i", Pk - ca.C, Nk)[:, None] / np.einsum("ikj,ij->ik", rays, Nk)
            Xg = ca.C + rays * t[..., None]
            uvb = _project(cb, lenses[b], Xg.reshape(-1, 3)).reshape(len(ua), -1, 2)
            pb = sample_bilinear(images[b], uvb[..., 0], uvb[..., 1]).astype(float)
            pa -= pa.mean(axis=1, keepdims=True)
            pb -= pb.mean(axis=1, keepdims=True)
            ncc = (pa * pb).sum(1) / np.sqrt((pa * pa).sum(1) * (pb * pb).sum(1) + 1e-9)
            result[f"{a}-{b}"] = {"median": float(np.median(ncc)), "points": int(len(ncc))}
    return result
