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

A camera is stable when every measure fits what the two calibrations can
resolve: by default the larger of three times their residual RMS and 2.5
times the measure's spread under no change, propagated from their IOP
covariances; or one threshold the user gives.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from .bundle import rodrigues
from .camera import Camera, distort, pixel_to_normalized

CRITERIA = ("zrot", "rot", "spr")


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
        or one of ``"zrot"``, ``"rot"``, ``"spr"`` alone.

    Returns the spec's ``{"cameras": {id: {zrot_px, rot_px, spr_px, stable}}}``
    with the thresholds used.
    """
    if criterion not in CRITERIA + ("all",):
        raise ValueError(f"unknown stability criterion {criterion!r}: choose all, {', '.join(CRITERIA)}")
    extra_a, extra_b = calib_a.extra or {}, calib_b.extra or {}
    res_a, res_b = extra_a.get("residual_rms_px", {}) or {}, extra_b.get("residual_rms_px", {}) or {}
    cov_a, cov_b = extra_a.get("iop_covariance", {}) or {}, extra_b.get("iop_covariance", {}) or {}
    out = {}
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
            base = default_threshold(res_a.get(cam_id), res_b.get(cam_id))
            thr = {k: base for k in names}
            if cam_id in cov_a and cam_id in cov_b:
                spread = null_spread(a, b, cov_a[cam_id], cov_b[cam_id], distance_mm)
                m["null_spread_px"] = spread
                thr = {k: max(base, k_sigma * spread[k]) for k in names}
        keys = CRITERIA if criterion == "all" else (criterion,)
        m["threshold_px"] = thr
        m["exceeds"] = [k for k in keys if m[f"{k}_px"] > thr[f"{k}_px"]]
        m["criterion"] = criterion
        m["stable"] = not m["exceeds"]
        out[cam_id] = m
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
        x = np.array([r["index"] for r in rows], dtype=float)
        trend[cam_id] = {k: (float(np.polyfit(x, [r[f"{k}_px"] for r in rows], 1)[0]) if len(rows) >= 2 else None)
                         for k in CRITERIA}
    return {"reference": reference, "cameras": series, "trend_px_per_calibration": trend,
            "verdict": {c: all(r["stable"] for r in rows) for c, rows in series.items()}}
