"""Rig calibration from test-field captures: targets, initial values, bundle adjustment.

The stages, each a function over arrays:

1. :func:`measure_targets` — ArUco detection and edge-fitted corners in every
   image, with the rejects counted by reason (unknown id, duplicate, poor edges);
2. :func:`initial_values` — IOPs from the nominal focal length, EOPs and
   test-field poses from space resection (``solvePnPRansac``) of every image;
   markers the resection cannot explain are rejected as misdetected, markers
   seen nearly edge-on are down-weighted or dropped;
3. :func:`calibrate` — the self-calibrating bundle adjustment
   (:mod:`recon_engine.bundle`) over all cameras and poses, once with corners
   measured in the distorted image, then again with corners re-measured in
   the image undistorted by the first solution.

The result is a :class:`recon_engine.formats.Calibration` in the pose-0 test
field frame with standard deviations, residuals and per-arm relative EOPs in
its extra keys.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field

import cv2
import numpy as np

from . import bundle
from .camera import Camera, camera_depth
from .formats import Calibration, Capture, FormatError, Rig, TestField, load_image
from .targets import detect_markers, refine_corners


@dataclass(frozen=True)
class CalibrationConfig:
    sigma_px: float = 0.1  # a priori precision of a measured corner coordinate
    min_markers: int = 6  # a camera that saw fewer markers over all poses is not calibrated
    edge_on_drop: float = 0.3  # drop markers whose normal is more than acos(0.3) = 73 deg off the view
    max_edge_rms_px: float = 0.6  # edge points scattered more than this: a poorly measured marker
    resection_reject_px: float = 4.0  # corners further than this from the resection are misdetections
    fixed_iop: tuple = ("k3",)  # IOPs held (k3 is inseparable from k1, k2 at 35 mm)
    reject_k: float = 4.0  # blunder threshold on standardized residuals
    correlation_warn: float = 0.95


@dataclass
class ImageTargets:
    """Markers measured in one image."""

    camera: str
    pose: int
    ids: np.ndarray  # (M,)
    corners: np.ndarray  # (M, 4, 2) px
    weights: np.ndarray = None  # (M,)
    coarse: np.ndarray = None  # (M, 4, 2) detector's corners (for re-measurement)


@dataclass
class CalibrationReport:
    dropped: dict = field(default_factory=dict)  # reason -> count
    dropped_by_camera: dict = field(default_factory=dict)  # camera -> reason -> count
    failed_cameras: dict = field(default_factory=dict)  # camera -> why
    warnings: list = field(default_factory=list)
    residual_rms_px: dict = field(default_factory=dict)  # camera -> px
    residual_rms_by_pose_px: dict = field(default_factory=dict)  # pose -> px
    sigma0: float = 0.0
    observations: int = 0
    inlier_fraction: float = 1.0
    iterations: int = 0
    converged: bool = True  # the last adjustment pass converged
    convergence: str = ""  # how it ended (bundle.Solution.reason)
    targets: list = field(default_factory=list, repr=False)  # the measurements adjusted (not serialized)

    def drop(self, camera, reason, n=1):
        if n <= 0:
            return
        self.dropped[reason] = self.dropped.get(reason, 0) + int(n)
        cam = self.dropped_by_camera.setdefault(camera, {})
        cam[reason] = cam.get(reason, 0) + int(n)

    def to_dict(self):
        return {k: v for k, v in self.__dict__.items() if k != "targets"}


def check_captures(captures: list[Capture], rig: Rig, testfield: TestField) -> None:
    """Refuse captures that are not test-field captures of this rig and test field."""
    if not captures:
        raise ValueError("no test-field capture given")
    seen = {}
    for cap in captures:
        src = cap.source
        if cap.kind != "testfield":
            raise FormatError(src, f"kind is {cap.kind!r}: calibration needs 'testfield' captures")
        if cap.testfield != testfield.name:
            raise FormatError(src, f"testfield is {cap.testfield!r}, but the test field given is {testfield.name!r}")
        if cap.rig != rig.serial:
            raise FormatError(src, f"rig is {cap.rig!r}, but rig.json is {rig.serial!r}")
        if cap.pose in seen:
            raise FormatError(src, f"pose {cap.pose} is also in {seen[cap.pose]}")
        seen[cap.pose] = src
    if 0 not in seen:
        raise ValueError("no capture of pose 0: pose 0 defines the calibration frame")


def _image_map(fn, items: list) -> list:
    """``fn`` over the images in threads (one per core the process may use), results in ``items``' order.

    Decoding an image and OpenCV's marker detection release the GIL. Measured on the 1000 x 667 px rig's
    60 images (whole calibration): 13.0 s with two threads against 13.8 s with one, a small gain; at paper
    scale it is not measured yet."""
    from concurrent.futures import ThreadPoolExecutor

    from .parallel import cores

    workers = min(cores(), len(items))
    if workers <= 1:
        return [fn(it) for it in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(fn, items))


def remeasure_targets(targets: list, images: dict, cameras: dict, report: CalibrationReport,
                      cfg: CalibrationConfig) -> list:
    """The same detections measured again, edges undistorted with ``cameras``' IOPs."""
    todo = [it for it in targets if it.camera in cameras and len(it.ids)]

    def remeasure(it):
        refined, rms, ok = refine_corners(images[(it.camera, it.pose)], it.coarse, cameras[it.camera])
        return refined, ok & (rms < cfg.max_edge_rms_px)

    out = []
    for it, (refined, good) in zip(todo, _image_map(remeasure, todo)):
        report.drop(it.camera, "poor_edges", (~good).sum())
        out.append(ImageTargets(it.camera, it.pose, it.ids[good], refined[good], np.ones(good.sum()), it.coarse[good]))
    return out


def measure_targets(captures, rig: Rig, testfield: TestField, report: CalibrationReport,
                    cfg: CalibrationConfig, cameras: dict | None = None, images: dict | None = None) -> list:
    """Markers of every image; ``cameras`` (IOPs) undistort the edges when given.

    ``images`` caches decoded images by (camera, pose) between passes. The images are measured in threads;
    what is dropped is counted in the images' order, so the report does not depend on the threads.
    """
    known = set(testfield.markers)
    todo = [(cap, cam_id) for cap in captures for cam_id in cap.cameras]

    def measure(item):
        cap, cam_id = item
        key = (cam_id, cap.pose)
        image = images.get(key) if images is not None else None
        if image is None:
            image = load_image(cap, cam_id, rig)
        drops = {}
        ids, coarse = detect_markers(image, testfield.aruco_dictionary)
        unknown = np.array([i not in known for i in ids], dtype=bool)
        drops["unknown_id"] = unknown.sum()
        ids, coarse = ids[~unknown], coarse[~unknown]
        uniq, counts = np.unique(ids, return_counts=True)
        dup = np.isin(ids, uniq[counts > 1])
        drops["duplicate_id"] = dup.sum()
        ids, coarse = ids[~dup], coarse[~dup]
        refined, rms, ok = refine_corners(image, coarse, None if cameras is None else cameras.get(cam_id))
        good = ok & (rms < cfg.max_edge_rms_px)
        drops["poor_edges"] = (~good).sum()
        return image, drops, ImageTargets(cam_id, cap.pose, ids[good], refined[good], np.ones(good.sum()), coarse[good])

    out = []
    for (cap, cam_id), (image, drops, targets) in zip(todo, _image_map(measure, todo)):
        if images is not None:
            images[(cam_id, cap.pose)] = image
        for reason, n in drops.items():
            report.drop(cam_id, reason, n)
        out.append(targets)
    return out


def _nominal_camera(rig: Rig, cam_id: str) -> Camera:
    spec = rig.cameras[cam_id]
    f = spec.nominal_focal_mm / spec.pixel_size_mm
    return Camera(spec.width, spec.height, f, f, (spec.width - 1) / 2, (spec.height - 1) / 2)


def _average_rotation(Rs):
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def initial_values(targets: list, rig: Rig, testfield: TestField, report: CalibrationReport,
                   cfg: CalibrationConfig, cameras: dict | None = None):
    """Initial cameras (IOPs nominal unless ``cameras`` given, EOPs by resection) and poses.

    Returns ``(cameras, poses)``: camera id -> Camera in the pose-0 frame, and
    pose -> (R, t) with ``X_pose0 = R @ X_field + t``. Drops misdetected and
    edge-on markers from ``targets`` (in place of their arrays) and sets weights.
    """
    resections = {}  # (camera, pose) -> (R, t) field -> camera
    for it in targets:
        if len(it.ids) < 4:
            continue
        cam = cameras[it.camera] if cameras and it.camera in cameras else _nominal_camera(rig, it.camera)
        obj = np.array([testfield.markers[i] for i in it.ids]).reshape(-1, 3)
        img = it.corners.reshape(-1, 2)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, cam.K, cam.dist, reprojectionError=cfg.resection_reject_px * 3,
                                                 iterationsCount=200, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < 8:
            report.drop(it.camera, "resection_failed", len(it.ids))
            it.ids, it.corners, it.weights, it.coarse = it.ids[:0], it.corners[:0], it.weights[:0], it.coarse[:0]
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl.ravel()], img[inl.ravel()], cam.K, cam.dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, cam.K, cam.dist)
        err = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1).reshape(-1, 4).max(axis=1)
        # tolerance grows with the uncorrected distortion of the first pass
        tol = cfg.resection_reject_px + (3 * np.median(err) if cameras is None else 0.0)
        mis = err > tol
        report.drop(it.camera, "misdetected", mis.sum())
        R = cv2.Rodrigues(rvec)[0]
        t = tvec.ravel()
        # foreshortening: weight by the cosine between marker normal and view ray
        quad = obj.reshape(-1, 4, 3)
        nrm = np.cross(quad[:, 1] - quad[:, 0], quad[:, 3] - quad[:, 0])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        centre_cam = quad.mean(axis=1) @ R.T + t
        view = centre_cam / np.linalg.norm(centre_cam, axis=1, keepdims=True)
        cosang = np.abs(np.einsum("ij,ij->i", nrm @ R.T, view))
        edge_on = cosang < cfg.edge_on_drop
        report.drop(it.camera, "edge_on", (edge_on & ~mis).sum())
        keep = ~mis & ~edge_on
        it.ids, it.corners, it.coarse = it.ids[keep], it.corners[keep], it.coarse[keep]
        it.weights = cosang[keep] ** 2
        resections[(it.camera, it.pose)] = (R, t)
    poses_present = sorted({p for _, p in resections})
    # test-field poses in the pose-0 frame, averaged over the cameras that saw both
    poses = {0: (np.eye(3), np.zeros(3))}
    for p in poses_present:
        if p == 0:
            continue
        Rs, ts = [], []
        for cam_id in rig.camera_ids:
            if (cam_id, 0) in resections and (cam_id, p) in resections:
                R0, t0 = resections[(cam_id, 0)]
                Rp, tp = resections[(cam_id, p)]
                Rs.append(R0.T @ Rp)
                ts.append(R0.T @ (tp - t0))
        if Rs:
            poses[p] = (_average_rotation(Rs), np.median(ts, axis=0))
    result = {}
    for cam_id in rig.camera_ids:
        for p, (Rk, tk) in poses.items():
            if (cam_id, p) in resections:
                Rc, tc = resections[(cam_id, p)]
                # x_cam = Rc X_field + tc, X_field = Rk^T (X0 - tk)
                R = Rc @ Rk.T
                t = tc - R @ tk
                base = cameras[cam_id] if cameras and cam_id in cameras else _nominal_camera(rig, cam_id)
                result[cam_id] = base.with_pose(R, -R.T @ t)
                break
    return result, poses


def _problem(targets, cameras, poses, testfield, cfg):
    cam_ids = sorted(cameras)
    cam_index = {c: i for i, c in enumerate(cam_ids)}
    pose_ids = sorted(poses)
    pose_index = {p: i for i, p in enumerate(pose_ids)}
    marker_ids = sorted(testfield.markers)
    marker_index = {m: i for i, m in enumerate(marker_ids)}
    uv, ci, pi, qi, wi = [], [], [], [], []
    for it in targets:
        if it.camera not in cam_index or it.pose not in pose_index or len(it.ids) == 0:
            continue
        n = len(it.ids)
        uv.append(it.corners.reshape(-1, 2))
        ci.append(np.full(4 * n, cam_index[it.camera]))
        pi.append(np.full(4 * n, pose_index[it.pose]))
        qi.append((np.array([marker_index[i] for i in it.ids])[:, None] * 4 + np.arange(4)).ravel())
        wi.append(np.repeat(it.weights, 4))
    cams = np.array([[c.fx, c.fy, c.cx, c.cy, *c.dist, *bundle.rotation_to_rvec(c.R), *c.C]
                     for c in (cameras[k] for k in cam_ids)])
    pose_arr = np.array([[*bundle.rotation_to_rvec(poses[p][0]), *poses[p][1]] for p in pose_ids])
    pose_arr[0] = 0.0
    points = np.array([testfield.markers[m] for m in marker_ids]).reshape(-1, 3)
    pb = bundle.Problem(np.vstack(uv), np.concatenate(ci), np.concatenate(pi), np.concatenate(qi),
                        np.concatenate(wi), cams, pose_arr, points, cfg.sigma_px, testfield.sigma_mm,
                        tuple(cfg.fixed_iop))
    return pb, cam_ids, pose_ids, marker_ids


def _cameras_from(sol, cam_ids, rig):
    out = {}
    for i, cam_id in enumerate(cam_ids):
        p = sol.cams[i]
        spec = rig.cameras[cam_id]
        out[cam_id] = Camera(spec.width, spec.height, p[0], p[1], p[2], p[3], p[4:9],
                             bundle.rodrigues(p[9:12]), p[12:15])
    return out


def arm_covariance(sol, cam_ids: list, rig: Rig) -> dict:
    """Per arm: its calibrated cameras and the joint covariance of their parameters.

    ``{arm: {"cameras": [...], "parameters": CAM_NAMES, "matrix": (15 n, 15 n)}}``
    in px, unitless, rad (Rodrigues vector world→camera) and mm (perspective centre).
    """
    out = {}
    n = bundle.N_CAM
    for arm in rig.arms:
        present = [c for c in arm.cameras if c in cam_ids]
        if not present:
            continue
        idx = np.concatenate([np.arange(n) + n * cam_ids.index(c) for c in present])
        # 7 significant digits: ample for propagating precision, half the size in calibration.json
        matrix = [[float(f"{v:.7g}") for v in row] for row in sol.cams_cov[np.ix_(idx, idx)]]
        out[arm.id] = {"cameras": present, "parameters": list(bundle.CAM_NAMES), "matrix": matrix}
    return out


def relative_eops(cameras: dict, rig: Rig) -> dict:
    """Each arm's cameras relative to its first camera: R_rel (first→camera), C in the first camera's frame (mm)."""
    out = {}
    for arm in rig.arms:
        present = [c for c in arm.cameras if c in cameras]
        if not present:
            continue
        first = cameras[present[0]]
        out[arm.id] = {"reference_camera": present[0], "cameras": {
            c: {"R": (cameras[c].R @ first.R.T).tolist(), "C": (first.R @ (cameras[c].C - first.C)).tolist()}
            for c in present}}
    return out


def calibrate(captures: list[Capture], rig: Rig, testfield: TestField, cfg: CalibrationConfig | None = None,
              progress=lambda msg: None):
    """Calibrate every camera of ``rig`` from test-field ``captures``.

    Returns ``(calibration, report)``. Cameras that saw too little are left
    out and named in ``report.failed_cameras``; the others are calibrated.
    Raises ``ValueError`` when no camera can be calibrated.
    """
    cfg = cfg or CalibrationConfig()
    check_captures(captures, rig, testfield)
    report = CalibrationReport()
    cache = {}
    progress("measuring targets")
    targets = measure_targets(captures, rig, testfield, report, cfg, images=cache)
    cameras, poses = initial_values(targets, rig, testfield, report, cfg)
    cameras = _keep_calibratable(targets, cameras, rig, report, cfg)
    sol = None
    for pass_ in range(2):
        progress(f"bundle adjustment, pass {pass_ + 1}")
        pb, cam_ids, pose_ids, marker_ids = _problem(targets, cameras, poses, testfield, cfg)
        sol = bundle.adjust(pb, reject_k=cfg.reject_k, correlation_warn=cfg.correlation_warn)
        if not sol.converged:
            report.warnings.append(f"bundle adjustment pass {pass_ + 1} did not converge: {sol.reason}")
        cameras = _cameras_from(sol, cam_ids, rig)
        poses = {p: (bundle.rodrigues(sol.poses[i, :3]), sol.poses[i, 3:]) for i, p in enumerate(pose_ids)}
        if pass_ == 0:
            # re-measure the corners with edges undistorted by the first solution
            progress("re-measuring targets with the estimated IOPs")
            targets = remeasure_targets(targets, cache, cameras, report, cfg)
            initial_values(targets, rig, testfield, report, cfg, cameras=cameras)
            _keep_calibratable(targets, cameras, rig, report, cfg)
    # figures
    for i, cam_id in enumerate(cam_ids):
        sel = (pb.cam == i) & sol.inlier
        report.residual_rms_px[cam_id] = float(np.sqrt(np.mean(sol.residuals[sel] ** 2))) if sel.any() else None
    for i, p in enumerate(pose_ids):
        sel = (pb.pose == i) & sol.inlier
        report.residual_rms_by_pose_px[str(p)] = float(np.sqrt(np.mean(sol.residuals[sel] ** 2))) if sel.any() else None
    report.sigma0 = sol.sigma0
    report.observations = int(len(pb.uv))
    report.inlier_fraction = float(sol.inlier.mean())
    report.iterations = sol.iterations
    report.converged, report.convergence = bool(sol.converged), sol.reason
    report.targets = targets
    report.drop("all", "blunder", int((~sol.inlier).sum() // 4))
    by_cam = {}
    for c, a, b, rho in sol.correlations:
        by_cam.setdefault(cam_ids[c], []).append(f"{a}/{b} {rho:+.2f}")
    for cam_id, pairs in by_cam.items():
        report.warnings.append(f"camera {cam_id}: high IOP-EOP correlations {', '.join(pairs)}")
    for cam_id in cam_ids:
        sel = (pb.cam == cam_ids.index(cam_id)) & sol.inlier
        spec = rig.cameras[cam_id]
        uv = pb.uv[sel]
        if len(uv) >= 3:
            hull = cv2.convexHull(uv.astype(np.float32))
            cover = cv2.contourArea(hull) / (spec.width * spec.height)
            if cover < 0.3:
                report.warnings.append(f"camera {cam_id}: targets cover only {cover:.0%} of the frame")
    extra = {
        "sigmas": {cam_id: dict(zip(bundle.CAM_NAMES, map(float, sol.cam_sigma[i]))) for i, cam_id in enumerate(cam_ids)},
        # covariance of fx, fy, cx, cy, k1, k2, p1, p2, k3 (px and unitless): what stability tests propagate
        "iop_covariance": {cam_id: sol.cam_cov[i][:9, :9].tolist() for i, cam_id in enumerate(cam_ids)},
        # joint covariance of each arm's cameras (CAM_NAMES per camera, in the arm's order): the
        # arm-frame stability measure propagates it, because the arm's cameras stay fixed in the arm
        "arm_covariance": arm_covariance(sol, cam_ids, rig),
        "residual_rms_px": report.residual_rms_px,
        "residual_rms_by_pose_px": report.residual_rms_by_pose_px,
        "sigma0": sol.sigma0,
        "sigma_px_a_priori": cfg.sigma_px,
        "arms": relative_eops(cameras, rig),
        "testfield": testfield.name,
        "testfield_poses": {str(p): {"R": R.tolist(), "t": t.tolist()} for p, (R, t) in poses.items()},
        "dropped_targets": report.dropped,
        "failed_cameras": report.failed_cameras,
        "warnings": report.warnings,
    }
    when = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()
    calib = Calibration(rig=rig.serial, calibrated_at=when, frame="testfield pose 0", cameras=cameras, extra=extra)
    return calib, report


def _keep_calibratable(targets, cameras, rig, report, cfg):
    """Cameras with enough markers; the others are named in the report and left out."""
    seen = {}
    for it in targets:
        seen.setdefault(it.camera, []).append(len(it.ids))
    keep = {}
    for cam_id in rig.camera_ids:
        n = sum(seen.get(cam_id, []))
        if cam_id not in cameras or n < cfg.min_markers:
            poses_seen = [it.pose for it in targets if it.camera == cam_id and len(it.ids)]
            report.failed_cameras[cam_id] = (
                f"saw {n} usable markers in {len(poses_seen)} pose(s); at least {cfg.min_markers} are needed")
            for it in targets:
                if it.camera == cam_id:
                    it.ids = it.ids[:0]
                    it.corners, it.weights, it.coarse = it.corners[:0], it.weights[:0], it.coarse[:0]
        else:
            keep[cam_id] = cameras[cam_id]
            report.failed_cameras.pop(cam_id, None)
    if not keep:
        raise ValueError("no camera could be calibrated: " + "; ".join(f"{k}: {v}" for k, v in report.failed_cameras.items()))
    return keep


def working_volume_points(radius_mm=250.0, height_mm=600.0, centre=(0.0, 0.0, 1068.0), n=2000, seed=0):
    """Points filling the working volume: a vertical cylinder at the rig centre."""
    rng = np.random.default_rng(seed)
    r = radius_mm * np.sqrt(rng.random(n))
    a = rng.random(n) * 2 * np.pi
    z = (rng.random(n) - 0.5) * height_mm
    return np.column_stack([r * np.cos(a), r * np.sin(a), z]) + np.asarray(centre)


def compare_cameras(est: Camera, true: Camera, points: np.ndarray) -> dict:
    """Differences of an estimated camera against the truth (figures of the calibration issue)."""
    vis = camera_depth(true, points) > 0
    p_true = true.project(points[vis])
    inside = (p_true[:, 0] >= 0) & (p_true[:, 0] < true.width) & (p_true[:, 1] >= 0) & (p_true[:, 1] < true.height)
    d = est.project(points[vis][inside]) - p_true[inside]
    dR = est.R @ true.R.T
    angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return {
        "image_rms_px": float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))),
        "principal_distance_rel": float(abs(0.5 * (est.fx + est.fy) / (0.5 * (true.fx + true.fy)) - 1)),
        "principal_point_px": float(np.hypot(est.cx - true.cx, est.cy - true.cy)),
        "centre_mm": float(np.linalg.norm(est.C - true.C)),
        "rotation_deg": float(angle),
    }
