"""Robust rigid registration of one torso to another (no scale: growth is real and must show).

Point-to-plane ICP with iteratively reweighted least squares: each pair's
weight is Tukey's biweight of its normal distance over a robust scale (1.4826
times the median absolute distance), so regions that really changed between
two visits get weight zero and cannot drag the fit; the acceptance distance
tightens with that scale. Pairs whose point projects off the fixed surface's
footprint (over a hole, beyond an edge) or whose normals disagree are not used.

Frames: the result ``(R, t)`` maps the moving torso's frame into the fixed
torso's frame, ``x_fixed = R @ x_moving + t`` (mm).
"""

from __future__ import annotations

import numpy as np

from .config import RigidConfig
from .torso import PlaneIndex, Torso


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (rad), Rodrigues' formula."""
    a = float(np.linalg.norm(w))
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (deg) of the rotation ``R``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def coarse_alignment(moving: Torso, fixed: Torso) -> tuple[np.ndarray, np.ndarray]:
    """Start of the registration: identity rotation, the horizontal centroids made to coincide.

    Both torsos stand upright in the same rig frame (+Z up), so rotation and
    height start at zero; the horizontal shift of a new placement in the rig
    (a few cm) is taken out by the centroids of the trunk's middle heights.
    """
    def centre(p):
        z0, z1 = np.percentile(p[:, 2], [25, 75])
        sel = p[(p[:, 2] >= z0) & (p[:, 2] <= z1)]
        return np.median(sel[:, :2], axis=0)

    t = np.zeros(3)
    t[:2] = centre(fixed.points) - centre(moving.points)
    return np.eye(3), t


def robust_scale(r: np.ndarray, floor: float) -> float:
    """1.4826 × median |r|, at least ``floor`` (mm)."""
    return max(floor, 1.4826 * float(np.median(np.abs(r)))) if len(r) else floor


def register_rigid(moving: Torso, fixed: Torso, cfg: RigidConfig | None = None, initial=None,
                   fixed_index: PlaneIndex | None = None, weights_mask: np.ndarray | None = None) -> dict:
    """Register ``moving`` to ``fixed`` rigidly and robustly.

    ``initial``: ``(R, t)`` start (default :func:`coarse_alignment`).
    ``weights_mask``: optional (N,) bool, the moving points allowed to take part.
    Returns ``{"R", "t", "iterations", "converged", "cycle" (the length of the cycle of poses the iterations
    stopped in, 0 if none), "scale_mm" (robust sigma of the normal distances), "pairs", "rms_mm"}``.
    """
    cfg = cfg or RigidConfig()
    index = fixed_index or PlaneIndex(fixed)
    R, t = initial if initial is not None else coarse_alignment(moving, fixed)
    R, t = np.asarray(R, float).copy(), np.asarray(t, float).copy()
    rng = np.random.default_rng(0)
    cand = np.arange(len(moving)) if weights_mask is None else np.nonzero(weights_mask)[0]
    if len(cand) > cfg.sample:
        cand = np.sort(rng.choice(cand, cfg.sample, replace=False))
    X, Nm = moving.points[cand], moving.normals[cand]
    dist_max = cfg.initial_distance_mm
    scale = dist_max / 3
    converged, it, cycle = False, 0, 0
    cos_max = np.cos(np.radians(cfg.max_normal_angle_deg))
    recent = []  # the last poses: the pair set can flip between a few states and repeat them for ever
    for it in range(1, cfg.max_iterations + 1):
        x = X @ R.T + t
        d, n, p, over = index.distances(x, cfg.max_tangential)
        ok = over & (np.abs(d) <= dist_max) & (np.sum((Nm @ R.T) * n, axis=1) >= cos_max)
        if ok.sum() < 50:
            raise ValueError(f"rigid registration: only {int(ok.sum())} point pairs within {dist_max:.1f} mm; "
                             "the torsos do not overlap")
        scale = robust_scale(d[ok], cfg.min_scale_mm)
        u = d[ok] / (cfg.tukey_c * scale)
        w = np.where(np.abs(u) < 1, (1 - u ** 2) ** 2, 0.0)
        xo, no, do = x[ok], n[ok], d[ok]
        c = xo.mean(axis=0)
        J = np.column_stack([np.cross(xo - c, no), no])
        A = J.T @ (J * w[:, None])
        b = -J.T @ (w * do)
        try:
            dx = np.linalg.solve(A + 1e-9 * np.eye(6), b)
        except np.linalg.LinAlgError:
            raise ValueError("rigid registration: singular normal equations (degenerate surface)") from None
        dR = rotation_from_vector(dx[:3])
        R = dR @ R
        t = dR @ (t - c) + c + dx[3:]
        dist_max = max(cfg.min_distance_mm, min(dist_max, cfg.tighten_k * cfg.tukey_c * scale))
        if np.degrees(np.linalg.norm(dx[:3])) < cfg.tol_rotation_deg and np.linalg.norm(dx[3:]) < cfg.tol_translation_mm:
            converged = True
            break
        # back (within the tolerances, with the same acceptance distance) to a pose of 2 to cfg.cycle_max
        # iterations ago: the iterations cycle through the same few pair sets and would only repeat them; stop
        # (not converged: the cycle's length is reported)
        cycle = next((lag for lag, (R0, t0, dist0) in enumerate(reversed(recent), start=1)
                      if lag >= 2 and dist0 == dist_max and rotation_angle_deg(R @ R0.T) < cfg.tol_rotation_deg
                      and np.linalg.norm(t - t0) < cfg.tol_translation_mm), 0)
        if cycle:
            break
        recent = [*recent, (R, t, dist_max)][-cfg.cycle_max:] if cfg.cycle_max else []
    # orthonormalize against round-off
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    return {"R": R, "t": t, "iterations": it, "converged": converged, "cycle": cycle, "scale_mm": float(scale),
            "pairs": int(ok.sum()), "rms_mm": float(np.sqrt(np.mean(d[ok] ** 2)))}
