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

A camera is stable when its measure fits the image measurement precision:
by default three times the combined residual RMS of the two calibrations,
with a floor, configurable.
"""

from __future__ import annotations

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


def default_threshold(rms_a: float | None, rms_b: float | None, factor: float = 3.0, floor_px: float = 0.25) -> float:
    """The image measurement precision both calibrations show, times ``factor``."""
    vals = [v for v in (rms_a, rms_b) if v is not None]
    if not vals:
        return max(floor_px, factor * 0.15)
    combined = np.sqrt(np.sum(np.square(vals)) * (2 / len(vals)) / 2)
    return float(max(floor_px, factor * combined))


def compare_calibrations(calib_a, calib_b, threshold_px: float | None = None, criterion: str = "zrot",
                         distance_mm: float = 2500.0) -> dict:
    """Stability of every camera both calibrations share.

    Parameters
    ----------
    calib_a, calib_b : formats.Calibration
        Earlier and later calibration.
    threshold_px : float, optional
        Largest offset of a stable camera; by default from the calibrations'
        own residual RMS (their ``residual_rms_px`` extra key) per camera.
    criterion : str
        Which measure decides the verdict: ``"zrot"`` (default: the cameras of
        an arm are used with their calibrated EOPs), ``"rot"`` or ``"spr"``.

    Returns the spec's ``{"cameras": {id: {zrot_px, rot_px, spr_px, stable}}}``
    plus the threshold and criterion used per camera.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"unknown stability criterion {criterion!r}: choose one of {', '.join(CRITERIA)}")
    res_a = (calib_a.extra or {}).get("residual_rms_px", {}) or {}
    res_b = (calib_b.extra or {}).get("residual_rms_px", {}) or {}
    out = {}
    for cam_id in sorted(set(calib_a.cameras) & set(calib_b.cameras)):
        a, b = calib_a.cameras[cam_id], calib_b.cameras[cam_id]
        if (a.width, a.height) != (b.width, b.height):
            raise ValueError(f"camera {cam_id}: image size {a.width}x{a.height} in the first calibration, "
                             f"{b.width}x{b.height} in the second")
        m = bundle_measures(a, b, distance_mm)
        thr = threshold_px if threshold_px is not None else default_threshold(res_a.get(cam_id), res_b.get(cam_id))
        m["threshold_px"] = thr
        m["criterion"] = criterion
        m["stable"] = bool(m[f"{criterion}_px"] <= thr)
        out[cam_id] = m
    return {"format": "torso-stability/1", "criterion": criterion, "cameras": out,
            "only_in_first": sorted(set(calib_a.cameras) - set(calib_b.cameras)),
            "only_in_second": sorted(set(calib_b.cameras) - set(calib_a.cameras))}


def history(calibrations: list, reference: str = "first", **kwargs) -> dict:
    """Measures of every calibration of each camera against its first or previous one.

    ``calibrations`` in time order. Returns ``{camera: [{"index", "calibrated_at",
    "zrot_px", "rot_px", "spr_px", "stable"}...], "trend": {camera: px per calibration}}``
    where the trend is the least-squares slope of the deciding measure.
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
        crit = rows[0]["criterion"]
        y = np.array([r[f"{crit}_px"] for r in rows])
        x = np.array([r["index"] for r in rows], dtype=float)
        trend[cam_id] = float(np.polyfit(x, y, 1)[0]) if len(rows) >= 2 else None
    return {"reference": reference, "cameras": series, "trend_px_per_calibration": trend,
            "verdict": {c: all(r["stable"] for r in rows) for c, rows in series.items()}}
