"""A COLMAP (pycolmap) peer for the arm reconstruction benchmark.

Reconstructs the sparse 3D points of one camera arm (K images, fully
calibrated cameras with known poses) with pycolmap's own pipeline, tuned for
dense coverage the way a competent COLMAP user would:

1. SIFT extraction (``pycolmap.extract_features``) with many features,
   upsampled first octave and a lowered peak threshold, one OPENCV camera per
   image holding the known intrinsics;
2. matching of the given image pairs only (``pycolmap.match_image_pairs`` with
   an imported pairs list), geometric verification (guided matching optional);
3. triangulation with the known, fixed poses (``pycolmap.triangulate_points``,
   the ``colmap point_triangulator``): poses and intrinsics stay fixed, only
   points are refined by the global bundle adjustment.

Run as a script to test it on the simulated ``bench-out/paper`` scenario
(distance of the points to the true body mesh).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np

__all__ = ["pycolmap_arm"]


def _as_uint8(img) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    return np.clip(img, 0, 255).astype(np.uint8)


def _sift_options(pycolmap, max_features, affine, dsp):
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 2
    opts.use_gpu = False
    opts.max_image_size = 100000  # never downscale the images
    sift = opts.sift
    sift.max_num_features = int(max_features)
    sift.first_octave = -1          # upsampled first octave: small blobs too
    sift.peak_threshold = 0.004     # default 0.0067: more, weaker features
    sift.max_num_orientations = 2
    if hasattr(sift, "estimate_affine_shape"):
        sift.estimate_affine_shape = bool(affine)
    if hasattr(sift, "domain_size_pooling"):
        sift.domain_size_pooling = bool(dsp)
    return opts


def _params(cam, model: str) -> list:
    """COLMAP's parameters of the camera's OpenCV model (fx, fy, cx, cy, k1, k2, p1, p2[, k3, k4, k5, k6])."""
    k1, k2, p1, p2, k3 = (float(v) for v in cam.dist)
    base = [cam.fx, cam.fy, cam.cx, cam.cy, k1, k2, p1, p2]
    return base + [k3, 0.0, 0.0, 0.0] if model == "FULL_OPENCV" else base


def pycolmap_arm(images: list, cameras: list, workdir, pairs=None, max_features=40000, *,
                 affine_shape=True, domain_size_pooling=True, keep_two_view_tracks=True,
                 guided_matching=False, num_threads=2) -> dict:
    """Sparse 3D points of one arm by COLMAP with the known cameras.

    Parameters
    ----------
    images : list of K (H, W) grey uint8 arrays.
    cameras : list of K ``recon_engine.camera.Camera`` (known IOPs and EOPs).
    workdir : directory for the images, the database and the model (emptied).
    pairs : list of (i, j) index pairs to match; default the neighbours
        (0, 1), (1, 2), ..., (K-2, K-1).
    max_features : SIFT features per image.
    affine_shape, domain_size_pooling : covariant SIFT options (slower, more
        robust to the oblique views).
    keep_two_view_tracks : triangulate points seen in only two images too
        (COLMAP drops them by default).
    guided_matching : COLMAP's guided matching after verification. Off by
        default: on the CPU it builds dense N1 x N2 descriptor-distance
        matrices (~14 GB per pair at 60k keypoints, OOM-killed here), so it
        only fits with far fewer features.

    Returns
    -------
    dict with ``points`` (N, 3) world mm, ``track_lengths`` (N,) int,
    ``seconds`` {extract, match, triangulate, total}.
    """
    import pycolmap

    K = len(images)
    if len(cameras) != K or K < 2:
        raise ValueError("need as many cameras as images, at least two")
    if pairs is None:
        pairs = [(i, i + 1) for i in range(K - 1)]

    t_start = time.perf_counter()
    workdir = Path(workdir)
    if workdir.exists():
        shutil.rmtree(workdir)
    image_dir = workdir / "images"
    model_dir = workdir / "sparse"
    image_dir.mkdir(parents=True)
    model_dir.mkdir(parents=True)
    database_path = workdir / "database.db"

    import cv2

    names = [f"img{i:02d}.png" for i in range(K)]
    for name, img in zip(names, images):
        if not cv2.imwrite(str(image_dir / name), _as_uint8(img)):
            raise OSError(f"cannot write {image_dir / name}")

    # --- 1. features ------------------------------------------------------
    t0 = time.perf_counter()
    # OPENCV holds the engine's five terms when k3 = 0 (our own calibrations); FULL_OPENCV (k1..k6 radial as a
    # ratio, here k4 = k5 = k6 = 0) the true lenses' k3
    model = "FULL_OPENCV" if any(abs(float(c.dist[4])) > 1e-12 for c in cameras) else "OPENCV"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    # one camera per image; the true intrinsics are written right below
    # (ImageReaderOptions holds a single camera_params string for all images)
    pycolmap.extract_features(
        database_path, image_dir, image_names=names,
        camera_mode=pycolmap.CameraMode.PER_IMAGE,
        reader_options=reader,
        extraction_options=_sift_options(pycolmap, max_features, affine_shape, domain_size_pooling),
        device=pycolmap.Device.cpu,
    )
    db = pycolmap.Database.open(database_path)
    db_images = {im.name: im for im in db.read_all_images()}
    image_ids, camera_ids = [], []
    for name, cam in zip(names, cameras):
        im = db_images[name]
        dbcam = db.read_camera(im.camera_id)
        if (dbcam.width, dbcam.height) != (cam.width, cam.height):
            raise ValueError(f"{name}: image is {dbcam.width}x{dbcam.height}, camera {cam.width}x{cam.height}")
        dbcam.params = _params(cam, model)
        dbcam.has_prior_focal_length = True
        db.update_camera(dbcam)
        image_ids.append(im.image_id)
        camera_ids.append(im.camera_id)
    n_keypoints = [db.num_keypoints_for_image(i) for i in image_ids]
    db.close()
    t_extract = time.perf_counter() - t0

    # --- 2. matching of the given pairs ------------------------------------
    t0 = time.perf_counter()
    pairs_path = workdir / "pairs.txt"
    pairs_path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    matching.guided_matching = bool(guided_matching)
    matching.max_num_matches = max(32768, int(max_features) * 2)
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pairs_path
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.num_threads = 1
    pycolmap.match_image_pairs(database_path, matching_options=matching, pairing_options=pairing,
                               verification_options=verification, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(database_path)
    n_inliers = {}
    for i, j in pairs:
        a, b = image_ids[i], image_ids[j]
        n_inliers[(i, j)] = int(db.read_two_view_geometry(a, b).inlier_matches.shape[0]) \
            if db.exists_two_view_geometry(a, b) else 0
    db.close()
    t_match = time.perf_counter() - t0

    # --- 3. triangulation with the known poses ------------------------------
    t0 = time.perf_counter()
    rec = pycolmap.Reconstruction()
    for name, cam, image_id, camera_id in zip(names, cameras, image_ids, camera_ids):
        pcam = pycolmap.Camera(camera_id=camera_id, model=model, width=int(cam.width),
                               height=int(cam.height), params=_params(cam, model))
        rec.add_camera_with_trivial_rig(pcam)
        R = np.asarray(cam.R, float)
        cam_from_world = pycolmap.Rigid3d(rotation=pycolmap.Rotation3d(R),
                                          translation=-R @ np.asarray(cam.C, float))
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=camera_id, image_id=image_id), cam_from_world)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.min_num_matches = 15
    opts.extract_colors = False
    opts.triangulation.ignore_two_view_tracks = not keep_two_view_tracks
    # the lenses are known: COLMAP must not take a large true k3 (the simulator's richer lenses reach |k3| > 1)
    # for a diverged estimate and leave the camera's images out (0 points otherwise)
    opts.max_extra_param = opts.mapper.max_extra_param = opts.triangulation.max_extra_param = 1e6
    rec = pycolmap.triangulate_points(rec, database_path, image_dir, model_dir,
                                      clear_points=True, options=opts, refine_intrinsics=False)
    ids = list(rec.points3D.keys())
    points = np.array([rec.points3D[p].xyz for p in ids], float).reshape(-1, 3)
    track_lengths = np.array([rec.points3D[p].track.length() for p in ids], int)
    # the poses must not have moved
    for image_id, cam in zip(image_ids, cameras):
        C = rec.images[image_id].projection_center()
        if np.linalg.norm(C - np.asarray(cam.C, float)) > 1e-6 * max(1.0, np.linalg.norm(cam.C)):
            raise RuntimeError("COLMAP moved a fixed pose")
    t_tri = time.perf_counter() - t0

    return {
        "points": points,
        "track_lengths": track_lengths,
        "seconds": {"extract": t_extract, "match": t_match, "triangulate": t_tri,
                    "total": time.perf_counter() - t_start},
        "num_keypoints": n_keypoints,
        "num_inlier_matches": n_inliers,
    }


def _main():
    import argparse
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from recon_engine.o3d import o3d

    from recon_engine.formats import load_image, read_calibration, read_capture, read_rig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="/work/main/bench-out/paper")
    ap.add_argument("--workdir", default="/tmp/peer_pycolmap")
    ap.add_argument("--max-features", type=int, default=40000)
    ap.add_argument("--no-affine", action="store_true")
    ap.add_argument("--no-dsp", action="store_true")
    ap.add_argument("--drop-two-view", action="store_true")
    ap.add_argument("--guided", action="store_true")
    args = ap.parse_args()

    S = args.scenario
    rig = read_rig(f"{S}/rig.json")
    cal = read_calibration(f"{S}/truth/visit0-a/calibration.json")
    cap = read_capture(f"{S}/captures/visit0-a", rig)
    ids = ["A1", "A2", "A3", "A4", "A5"]
    cams = [cal.cameras[c] for c in ids]
    imgs = [load_image(cap, c, rig) for c in ids]

    out = pycolmap_arm(imgs, cams, args.workdir, max_features=args.max_features,
                       affine_shape=not args.no_affine, domain_size_pooling=not args.no_dsp,
                       keep_two_view_tracks=not args.drop_two_view, guided_matching=args.guided)
    points = out["points"]

    mesh = o3d.t.io.read_triangle_mesh(f"{S}/truth/visit0-a/body.ply")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    d = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy() if len(points) else np.zeros(0)

    print(f"keypoints per image: {out['num_keypoints']}")
    print(f"inlier matches per pair: {out['num_inlier_matches']}")
    tl = out["track_lengths"]
    print(f"points: {len(points)}  track lengths: " +
          ", ".join(f"{k}:{int((tl == k).sum())}" for k in sorted(set(tl.tolist()))))
    if len(d):
        print(f"distance to body mesh (mm): RMS {np.sqrt(np.mean(d ** 2)):.3f}  "
              f"median {np.median(d):.3f}  p95 {np.percentile(d, 95):.3f}  max {d.max():.3f}")
    print("seconds: " + "  ".join(f"{k} {v:.1f}" for k, v in out["seconds"].items()))


if __name__ == "__main__":
    _main()
