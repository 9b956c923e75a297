"""Camera stability: the bundle-similarity measures of Habib and Morgan (2005).

Two calibrations of one camera give two bundles of rays. Each measure
compares them over a grid covering the frame, after removing what a given
use of the camera can absorb, and reports the RMS offset in pixels between
where the two bundles put the same ray:

ZROT
    same perspective centre, parallel axes: only the IOPs differ. The
    criterion for a camera used with fixed EOPs, as the cameras inside an arm.
ROT
    same perspective centre, the best rotation between the bundles removed.
SPR
    single-photo resection: the best full EOP removed (rays of the first
    bundle meet a plane at the working distance; the second camera is
    resected on those points).

A fourth measure fits how the rig uses its cameras:

ARM
    the camera's whole bundle (IOPs and EOPs) in its arm's frame: the arm's
    other cameras fix the arm's rigid motion between the calibrations (the
    motion that best superimposes their bundles), and the camera's rays at
    the working distance are compared after that motion. The arm's cameras
    stay fixed in the arm and their relative EOPs are carried from the
    calibration into every reconstruction, so this is the offset a
    reconstruction would suffer. It also sees what ZROT cannot resolve
    with fixed cameras: a principal-point shift that the adjustment puts
    partly into the camera's rotation (the two are correlated at 0.97–0.99
    when the cameras do not move) still turns the camera's rays in the arm.

A camera is stable when every measure fits what the two calibrations can
resolve: by default the larger of three times their residual RMS and 2.5
times the measure's spread under no change, propagated from their IOP
covariances (ARM: from the joint covariance of the arm's cameras); or one
threshold the user gives.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from .bundle import CAM_STEP, CAM_NAMES, rodrigues, rotation_to_rvec
from .camera import Camera, distort, pixel_to_normalized, project

CRITERIA = ("zrot", "rot", "spr", "arm")


def _grid(camera: Camera, nx: int = 21, ny: int = 15, margin: float = 0.02):
    u = np.linspace(margin * camera.width, (1 - margin) * (camera.width - 1), nx)
    v = np.linspace(margin * camera.height, (1 - margin) * (camera.height - 1), ny)
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


def _image(camera: Camera, d_cam: np.ndarray) -> np.ndarray:
    """Pixels of camera-frame directions (N, 3) with the camera's IOPs."""
    xy = d_cam[:, :2] / d_cam[:, 2:3]
    xyd = distort(xy, camera.dist)
    return np.column_stack([camera.fx * xyd[:, 0] + camera.cx, camera.fy * xyd[:, 1] + camera.cy])


def _rms(offsets):
    return float(np.sqrt(np.mean(np.sum(offsets ** 2, axis=1))))


def bundle_measures(a: Camera, b: Camera, distance_mm: float = 2500.0) -> dict:
    """ZROT, ROT and SPR (px, RMS offsets) between the bundles of ``a`` and ``b``.

    Only the IOPs of ``a`` and ``b`` matter (each measure fixes or fits the
    EOP itself); ``distance_mm`` is the depth of the plane for SPR.
    """
    grid = _grid(a)
    xy = pixel_to_normalized(a, grid)
    rays = np.column_stack([xy, np.ones(len(xy))])
    zrot = _rms(_image(b, rays) - grid)

    def rot_residual(w):
        return (_image(b, rays @ rodrigues(w).T) - grid).ravel()

    rot_fit = least_squares(rot_residual, np.zeros(3), x_scale=1e-3)
    rot = _rms(rot_fit.fun.reshape(-1, 2))

    # SPR: object points on a plane at the working distance, resected by b
    X = rays * (distance_mm / rays[:, 2:3])

    def spr_residual(p):
        xc = X @ rodrigues(p[:3]).T + p[3:]
        return (_image(b, xc) - grid).ravel()

    spr_fit = least_squares(spr_residual, np.zeros(6), x_scale=np.array([1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0]))
    spr = _rms(spr_fit.fun.reshape(-1, 2))
    return {"zrot_px": zrot, "rot_px": rot, "spr_px": spr}


IOP_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_IOP_STEP = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6])


def _with_iop(cam: Camera, v) -> Camera:
    return replace(cam, fx=v[0], fy=v[1], cx=v[2], cy=v[3], dist=np.asarray(v[4:9]))


def _iop(cam: Camera) -> np.ndarray:
    return np.array([cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist])


def null_spread(a: Camera, b: Camera, cov_a, cov_b, distance_mm: float = 2500.0) -> dict:
    """Standard deviation (px) of each measure when nothing changed, from the IOP covariances.

    Linear propagation: the grid offsets' covariance from both calibrations'
    IOP covariances; for ROT and SPR, the part a rotation (ROT) or a full
    resection (SPR) would absorb is projected out first.
    """
    grid = _grid(a)
    n = len(grid)

    def offsets(va, vb, pose=np.zeros(6), plane=False):
        ca, cb = _with_iop(a, va), _with_iop(b, vb)
        xy_a = pixel_to_normalized(ca, grid)
        r = np.column_stack([xy_a, np.ones(n)])
        if plane:
            r = r * distance_mm
        xc = r @ rodrigues(pose[:3]).T + pose[3:]
        return (_image(cb, xc) - grid).ravel()

    va, vb = _iop(a), _iop(b)
    Ja = np.column_stack([(offsets(va + e, vb) - offsets(va - e, vb)) / (2 * h)
                          for e, h in ((np.eye(9)[k] * _IOP_STEP[k], _IOP_STEP[k]) for k in range(9))])
    Jb = np.column_stack([(offsets(va, vb + e) - offsets(va, vb - e)) / (2 * h)
                          for e, h in ((np.eye(9)[k] * _IOP_STEP[k], _IOP_STEP[k]) for k in range(9))])
    C = Ja @ np.asarray(cov_a) @ Ja.T + Jb @ np.asarray(cov_b) @ Jb.T

    def absorbed(G):
        P = np.eye(2 * n) - G @ np.linalg.pinv(G)
        return P @ C @ P.T

    steps = np.array([1e-6, 1e-6, 1e-6, 1e-3, 1e-3, 1e-3])
    G_rot = np.column_stack([(offsets(va, vb, np.eye(6)[k] * steps[k]) - offsets(va, vb, -np.eye(6)[k] * steps[k]))
                             / (2 * steps[k]) for k in range(3)])
    G_spr = np.column_stack([(offsets(va, vb, np.eye(6)[k] * steps[k], True) - offsets(va, vb, -np.eye(6)[k] * steps[k], True))
                             / (2 * steps[k]) for k in range(6)])
    return {"zrot_px": float(np.sqrt(np.trace(C) / n)),
            "rot_px": float(np.sqrt(max(np.trace(absorbed(G_rot)), 0) / n)),
            "spr_px": float(np.sqrt(max(np.trace(absorbed(G_spr)), 0) / n))}


def _params(cam: Camera) -> np.ndarray:
    """The camera as the adjustment's parameter vector (``CAM_NAMES``)."""
    return np.array([cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist, *rotation_to_rvec(cam.R), *cam.C])


def _camera(template: Camera, p) -> Camera:
    return replace(template, fx=p[0], fy=p[1], cx=p[2], cy=p[3], dist=np.asarray(p[4:9]),
                   R=rodrigues(p[9:12]), C=np.asarray(p[12:15]))


_MOTION_STEP = np.array([1e-7, 1e-7, 1e-7, 1e-3, 1e-3, 1e-3])


def _ray_points(template: Camera, grid, pa, distance_mm: float) -> np.ndarray:
    """World points (N, 3, mm) where calibration ``pa``'s rays of ``grid`` reach ``distance_mm``."""
    ca = _camera(template, pa)
    xy = pixel_to_normalized(ca, grid)
    d = np.column_stack([xy, np.ones(len(xy))]) @ ca.R  # camera→world directions
    return ca.C + distance_mm * d / np.linalg.norm(d, axis=1, keepdims=True)


def _offsets(template: Camera, grid, X_a, pb, motion) -> np.ndarray:
    """Pixel offsets (2N,) of calibration ``pb``'s images of ``X_a`` (world a) from ``grid``.

    ``motion`` = (R, t) carries world a into world b (the arm's rigid motion).
    """
    R, t = motion
    return (project(_camera(template, pb), X_a @ R.T + t) - grid).ravel()


def _compose(motion0, m):
    R0, t0 = motion0
    return rodrigues(m[:3]) @ R0, t0 + m[3:]


def _initial_motion(pairs):
    """Rigid motion world a → world b from the cameras' rotations and centres (chordal mean)."""
    M = sum(cb.R.T @ ca.R for ca, cb in pairs)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    t = np.mean([cb.C - R @ ca.C for ca, cb in pairs], axis=0)
    return R, t


def _fit_motion(cams, motion0, G, iterations: int = 3):
    """Gauss–Newton for the motion that best superimposes the bundles of ``cams``.

    ``cams`` holds each camera's (template, grid, X_a, pb); ``G`` their offsets'
    derivatives by the motion's 6 parameters (rotation vector rad, mm) at
    ``motion0``; the motion is small, so they serve every iteration.
    """
    Gs = np.vstack(G)
    motion = motion0
    for _ in range(iterations):
        o = np.concatenate([_offsets(tm, g, X, pb, motion) for tm, g, X, pb in cams])
        dm = np.linalg.lstsq(Gs, -o, rcond=None)[0]
        motion = _compose(motion, dm)
        if np.abs(dm[:3]).max() < 1e-10 and np.abs(dm[3:]).max() < 1e-6:
            break
    return motion


def _jacobians(tm, grid, pa, pb, X_a, motion, distance_mm):
    """d offsets / d (pa, pb, motion) by central differences: (2N, 15), (2N, 15), (2N, 6)."""
    eye15 = np.eye(15)
    Ja = np.column_stack([
        (_offsets(tm, grid, _ray_points(tm, grid, pa + h, distance_mm), pb, motion)
         - _offsets(tm, grid, _ray_points(tm, grid, pa - h, distance_mm), pb, motion)) / (2 * h[k])
        for k, h in ((k, eye15[k] * CAM_STEP[k]) for k in range(15))])
    Jb = np.column_stack([
        (_offsets(tm, grid, X_a, pb + h, motion) - _offsets(tm, grid, X_a, pb - h, motion)) / (2 * h[k])
        for k, h in ((k, eye15[k] * CAM_STEP[k]) for k in range(15))])
    return Ja, Jb, _motion_jacobian(tm, grid, X_a, pb, motion)


def _motion_jacobian(tm, grid, X_a, pb, motion):
    """d offsets / d motion (rotation vector rad, mm) by central differences: (2N, 6)."""
    eye6 = np.eye(6)
    return np.column_stack([
        (_offsets(tm, grid, X_a, pb, _compose(motion, h)) - _offsets(tm, grid, X_a, pb, _compose(motion, -h))) / (2 * h[k])
        for k, h in ((k, eye6[k] * _MOTION_STEP[k]) for k in range(6))])


def _arm_cov(extra: dict, arm: str, cameras: list):
    """Joint covariance (15 n, 15 n) of ``cameras`` from a calibration's ``arm_covariance``, or None."""
    block = ((extra or {}).get("arm_covariance") or {}).get(arm)
    if not block or list(block.get("parameters", [])) != list(CAM_NAMES) or not set(cameras) <= set(block["cameras"]):
        return None
    idx = np.concatenate([np.arange(15) + 15 * block["cameras"].index(c) for c in cameras])
    return np.asarray(block["matrix"], dtype=float)[np.ix_(idx, idx)]


def arm_measures(calib_a, calib_b, base_threshold: dict, distance_mm: float = 2500.0, k_sigma: float = 2.5,
                 threshold_px: float | None = None) -> dict:
    """The ARM measure (px, RMS offset) of every camera that both calibrations place in an arm.

    Each camera is compared after the arm's motion fitted on the arm's other
    cameras (at least two), so the camera under test cannot hide its own
    change in the fit. A disturbed camera would still drag the fits of its
    neighbours, so the cameras are excluded one at a time, the worst first
    (largest measure against its threshold), from the others' fits until no
    camera left in them exceeds its threshold (data snooping).
    ``base_threshold`` holds each camera's floor (px); without
    ``threshold_px``, a camera's threshold is the larger of its floor and
    ``k_sigma`` times the measure's spread under no change, propagated from
    both calibrations' joint arm covariances (``arm_covariance``).

    Returns ``{camera: {"arm_px", "arm_null_spread_px", "arm_threshold_px",
    "arm_reference_cameras"}}``; cameras without an arm or with fewer than two
    other cameras are absent.
    """
    arms_a = (calib_a.extra or {}).get("arms") or {}
    arms_b = (calib_b.extra or {}).get("arms") or {}
    out = {}
    for arm in sorted(set(arms_a) & set(arms_b)):
        members = [c for c in arms_a[arm]["cameras"] if c in arms_b[arm]["cameras"]
                   and c in calib_a.cameras and c in calib_b.cameras]
        if len(members) < 3:
            continue
        data = {}
        for c in members:
            tm = calib_a.cameras[c]
            pa, pb = _params(tm), _params(calib_b.cameras[c])
            grid = _grid(tm)
            data[c] = (tm, grid, pa, pb, _ray_points(tm, grid, pa, distance_mm))
        # one linearization point for the whole arm: the motion fitted on all its cameras
        motion0 = _initial_motion([(_camera(d[0], d[2]), _camera(d[0], d[3])) for d in data.values()])
        G0 = [_motion_jacobian(d[0], d[1], d[4], d[3], motion0) for d in data.values()]
        motion_all = _fit_motion([(d[0], d[1], d[4], d[3]) for d in data.values()], motion0, G0)
        jac = {c: _jacobians(*data[c][:4], data[c][4], motion_all, distance_mm) for c in members}
        cov_a = _arm_cov(calib_a.extra, arm, members)
        cov_b = _arm_cov(calib_b.extra, arm, members)
        excluded: list = []
        while True:
            result = {}
            for c in members:
                others = [o for o in members if o != c and o not in excluded]
                if len(others) < 2:
                    others = [o for o in members if o != c][:max(2, len(others))]
                motion = _fit_motion([(data[o][0], data[o][1], data[o][4], data[o][3]) for o in others],
                                     motion_all, [jac[o][2] for o in others])
                tm, grid, _, pb, X_a = data[c]
                value = _rms(_offsets(tm, grid, X_a, pb, motion).reshape(-1, 2))
                row = {"arm_px": value, "arm_reference_cameras": others}
                thr = base_threshold.get(c, 0.25) if threshold_px is None else float(threshold_px)
                if threshold_px is None and cov_a is not None and cov_b is not None:
                    spread = _arm_null_spread(jac, c, others, members, cov_a, cov_b)
                    row["arm_null_spread_px"] = spread
                    thr = max(thr, k_sigma * spread)
                row["arm_threshold_px"] = thr
                result[c] = row
            worst = max((c for c in members if c not in excluded), key=lambda c: result[c]["arm_px"] / result[c]["arm_threshold_px"])
            if result[worst]["arm_px"] <= result[worst]["arm_threshold_px"] or len(members) - len(excluded) <= 3:
                break
            excluded.append(worst)
        out.update(result)
    return out


def _arm_null_spread(jac, c, others, members, cov_a, cov_b) -> float:
    """Spread (px) of camera ``c``'s ARM measure under no change, by linear propagation.

    The offsets of ``c`` depend on its own parameters in both calibrations and,
    through the fitted motion, on the parameters of ``others``:
    ``o_c = J_c θ - G_c H⁻¹ Σ_o G_oᵀ J_o θ`` with ``H = Σ_o G_oᵀ G_o``.
    """
    H = sum(jac[o][2].T @ jac[o][2] for o in others)
    Hinv_G = np.linalg.solve(H, jac[c][2].T).T  # G_c H^-1
    n = jac[c][0].shape[0]
    A_a = np.zeros((n, 15 * len(members)))
    A_b = np.zeros_like(A_a)
    k = members.index(c)
    A_a[:, 15 * k: 15 * k + 15] = jac[c][0]
    A_b[:, 15 * k: 15 * k + 15] = jac[c][1]
    for o in others:
        k = members.index(o)
        A_a[:, 15 * k: 15 * k + 15] -= Hinv_G @ (jac[o][2].T @ jac[o][0])
        A_b[:, 15 * k: 15 * k + 15] -= Hinv_G @ (jac[o][2].T @ jac[o][1])
    var = np.einsum("ij,jk,ik->", A_a, cov_a, A_a) + np.einsum("ij,jk,ik->", A_b, cov_b, A_b)
    return float(np.sqrt(max(var, 0.0) / (n // 2)))


def default_threshold(rms_a: float | None, rms_b: float | None, factor: float = 3.0, floor_px: float = 0.25) -> float:
    """The image measurement precision both calibrations show, times ``factor``."""
    vals = [v for v in (rms_a, rms_b) if v is not None]
    if not vals:
        return max(floor_px, factor * 0.15)
    return float(max(floor_px, factor * np.sqrt(np.mean(np.square(vals)))))


def compare_calibrations(calib_a, calib_b, threshold_px: float | None = None, criterion: str = "all",
                         distance_mm: float = 2500.0, k_sigma: float = 2.5) -> dict:
    """Stability of every camera both calibrations share.

    Parameters
    ----------
    calib_a, calib_b : formats.Calibration
        Earlier and later calibration.
    threshold_px : float, optional
        Largest offset (px) of a stable camera, for every measure. By default
        each measure gets its own: the larger of three times the calibrations'
        residual RMS (``residual_rms_px``) and ``k_sigma`` times the measure's
        spread under no change, propagated from both calibrations' IOP
        covariances (``iop_covariance``) where they carry them. A change the
        calibrations cannot resolve is then not called instability.
    criterion : str
        ``"all"`` (default: unstable when any measure exceeds its threshold),
        or one of ``"zrot"``, ``"rot"``, ``"spr"``, ``"arm"`` alone.

    Returns the spec's ``{"cameras": {id: {zrot_px, rot_px, spr_px, stable}}}``
    with the thresholds used, and ``arm_px`` for every camera whose arm has at
    least two other cameras in both calibrations (the calibrations' ``arms``).
    With ``criterion="arm"``, a camera without the ARM measure has
    ``stable`` None: it was not judged.
    """
    if criterion not in CRITERIA + ("all",):
        raise ValueError(f"unknown stability criterion {criterion!r}: choose all, {', '.join(CRITERIA)}")
    extra_a, extra_b = calib_a.extra or {}, calib_b.extra or {}
    res_a, res_b = extra_a.get("residual_rms_px", {}) or {}, extra_b.get("residual_rms_px", {}) or {}
    cov_a, cov_b = extra_a.get("iop_covariance", {}) or {}, extra_b.get("iop_covariance", {}) or {}
    out, base = {}, {}
    for cam_id in sorted(set(calib_a.cameras) & set(calib_b.cameras)):
        a, b = calib_a.cameras[cam_id], calib_b.cameras[cam_id]
        if (a.width, a.height) != (b.width, b.height):
            raise ValueError(f"camera {cam_id}: image size {a.width}x{a.height} in the first calibration, "
                             f"{b.width}x{b.height} in the second")
        m = bundle_measures(a, b, distance_mm)
        names = list(m)
        if threshold_px is not None:
            thr = {k: float(threshold_px) for k in names}
        else:
            base[cam_id] = default_threshold(res_a.get(cam_id), res_b.get(cam_id))
            thr = {k: base[cam_id] for k in names}
            if cam_id in cov_a and cam_id in cov_b:
                spread = null_spread(a, b, cov_a[cam_id], cov_b[cam_id], distance_mm)
                m["null_spread_px"] = spread
                thr = {k: max(base[cam_id], k_sigma * spread[k]) for k in names}
        m["threshold_px"] = thr
        out[cam_id] = m
    if criterion in ("all", "arm"):
        for cam_id, row in arm_measures(calib_a, calib_b, base, distance_mm, k_sigma, threshold_px).items():
            m = out[cam_id]
            m["arm_px"] = row["arm_px"]
            m["arm_reference_cameras"] = row["arm_reference_cameras"]
            m["threshold_px"]["arm_px"] = row["arm_threshold_px"]
            if "arm_null_spread_px" in row:
                m.setdefault("null_spread_px", {})["arm_px"] = row["arm_null_spread_px"]
    for cam_id, m in out.items():
        keys = [k for k in (CRITERIA if criterion == "all" else (criterion,)) if f"{k}_px" in m]
        m["exceeds"] = [k for k in keys if m[f"{k}_px"] > m["threshold_px"][f"{k}_px"]]
        m["criterion"] = criterion
        m["stable"] = not m["exceeds"] if keys else None
    return {"format": "torso-stability/1", "criterion": criterion, "cameras": out,
            "only_in_first": sorted(set(calib_a.cameras) - set(calib_b.cameras)),
            "only_in_second": sorted(set(calib_b.cameras) - set(calib_a.cameras))}


def history(calibrations: list, reference: str = "first", **kwargs) -> dict:
    """Measures of every calibration of each camera against its first or previous one.

    ``calibrations`` in time order. Returns ``{"cameras": {camera: [rows]},
    "trend_px_per_calibration": {camera: {measure: slope}}, "verdict": {camera: bool}}``;
    the trend is the least-squares slope of each measure over the calibrations.
    """
    if reference not in ("first", "previous"):
        raise ValueError("reference must be 'first' or 'previous'")
    series: dict = {}
    for i in range(1, len(calibrations)):
        base = calibrations[0] if reference == "first" else calibrations[i - 1]
        result = compare_calibrations(base, calibrations[i], **kwargs)
        for cam_id, m in result["cameras"].items():
            series.setdefault(cam_id, []).append({"index": i, "calibrated_at": calibrations[i].calibrated_at, **m})
    trend = {}
    for cam_id, rows in series.items():
        trend[cam_id] = {}
        for k in CRITERIA:
            have = [r for r in rows if r.get(f"{k}_px") is not None]
            trend[cam_id][k] = (float(np.polyfit([r["index"] for r in have], [r[f"{k}_px"] for r in have], 1)[0])
                                if len(have) >= 2 else None)
    return {"reference": reference, "cameras": series, "trend_px_per_calibration": trend,
            "verdict": {c: all(r["stable"] is not False for r in rows) for c, rows in series.items()}}
