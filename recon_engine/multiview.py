"""Least-squares multi-ray intersection with blunder rejection.

Each track (one surface point seen in several images) is intersected from
all its rays at once, in original image coordinates through the cameras'
lens distortion (collinearity equations). A linear solution (the point
closest to all rays) starts a Gauss–Newton adjustment; the point's
covariance follows from the normal equations. A ray whose residual fails a
chi-square test is removed and the point solved again; points that stay
inconsistent, or keep fewer than two rays, are dropped.

Units: mm in the world frame (the calibration's), px in the images.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from .camera import Camera, distort, distort_jacobian, pixel_to_ray
from .parallel import cores


@dataclass(frozen=True)
class IntersectionConfig:
    sigma_px: float = 0.1  # a priori precision of a matched image coordinate
    chi2_ray: float = 13.8  # chi-square(2 dof) at 99.9%: a ray's squared standardized residual above it is a blunder
    iterations: int = 5  # Gauss–Newton iterations (converges in 2–3 from the linear start)
    min_rays: int = 2
    min_angle_deg: float = 2.0  # points whose rays meet at a smaller angle are too weak in depth
    threads: int = 0  # the tracks are intersected in this many blocks at once (0: one per core)


def linear_intersection(centres: np.ndarray, directions: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Points (T, 3) closest in the least-squares sense to their rays.

    ``centres`` (K, 3) perspective centres, ``directions`` (T, K, 3) unit rays
    (world frame), ``valid`` (T, K) which rays exist.
    """
    d = np.where(valid[..., None], directions, 0.0)
    P = np.eye(3)[None, None] - d[..., :, None] * d[..., None, :]  # (T, K, 3, 3)
    P = P * valid[..., None, None]
    A = P.sum(axis=1)
    b = np.einsum("tkij,kj->ti", P, centres)
    A = A + np.eye(3)[None] * 1e-12
    return np.linalg.solve(A, b[..., None])[..., 0]


def project_with_jacobian(cam: Camera, X: np.ndarray):
    """Pixels (N, 2) of world points (mm) and d(pixel)/dX (N, 2, 3), analytic (collinearity with distortion)."""
    xc = (np.asarray(X, dtype=float) - cam.C) @ cam.R.T
    z = xc[:, 2]
    x, y = xc[:, 0] / z, xc[:, 1] / z
    xyd = distort(np.column_stack([x, y]), cam.dist)
    uv = np.column_stack([cam.fx * xyd[:, 0] + cam.cx, cam.fy * xyd[:, 1] + cam.cy])
    a, b, c, d = distort_jacobian(x, y, np.asarray(cam.dist, dtype=float))
    # d(x, y)/d(camera-frame point), then through the rotation to the world frame
    P = np.zeros((len(z), 2, 3))
    P[:, 0, 0] = 1 / z
    P[:, 0, 2] = -x / z
    P[:, 1, 1] = 1 / z
    P[:, 1, 2] = -y / z
    D = np.stack([np.stack([cam.fx * a, cam.fx * b], axis=-1), np.stack([cam.fy * c, cam.fy * d], axis=-1)], axis=1)
    return uv, D @ P @ cam.R


def intersect(cameras: list[Camera], observations: np.ndarray, cfg: IntersectionConfig | None = None) -> dict:
    """Intersect tracks from their image observations.

    Parameters
    ----------
    cameras : list of K Camera
        IOPs and EOPs (world→camera) of the images, in the observations' order.
    observations : (T, K, 2) array
        Original (distorted) pixel coordinates; NaN where a track has no ray.

    Returns a dict with ``X`` (T, 3) mm, ``cov`` (T, 3, 3) mm², ``rays`` (T,)
    rays kept, ``used`` (T, K) bool, ``residual_px`` (T, K, 2), ``sigma0``
    (T,) per-point a-posteriori standard deviation of unit weight,
    ``valid`` (T,) bool and ``reason`` (T,) why a point was dropped ("" if kept).
    """
    cfg = cfg or IntersectionConfig()
    obs = np.asarray(observations, dtype=float)
    T, K, _ = obs.shape
    if K != len(cameras):
        raise ValueError(f"observations have {K} images but {len(cameras)} cameras are given")
    threads = cores(cfg.threads)
    if threads > 1 and T >= 2000:
        # every track is solved on its own: blocks in threads (numpy releases the GIL in the array work)
        one = replace(cfg, threads=1)
        with ThreadPoolExecutor(threads) as pool:
            parts = list(pool.map(lambda block: intersect(cameras, block, one), np.array_split(obs, threads)))
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    used = np.isfinite(obs).all(axis=2)
    centres = np.array([c.C for c in cameras])
    dirs = np.zeros((T, K, 3))
    for k, cam in enumerate(cameras):
        sel = used[:, k]
        if sel.any():
            dirs[sel, k] = pixel_to_ray(cam, obs[sel, k])
    X = linear_intersection(centres, dirs, used)
    res = np.zeros((T, K, 2))
    N = np.zeros((T, 3, 3))
    reason = np.full(T, "", dtype=object)
    reason[used.sum(axis=1) < cfg.min_rays] = "fewer than two rays"
    # only tracks with enough rays are adjusted, and after the first round only those that lost a ray
    redo = np.nonzero(reason == "")[0]
    for _ in range(K):  # at most one ray removed per point per round
        if len(redo) == 0:
            break
        X[redo], N[redo], res[redo] = _adjust(cameras, obs[redo], used[redo], X[redo], cfg.iterations)
        z = np.sum(res ** 2, axis=2) / cfg.sigma_px ** 2
        z = np.where(used, z, -1)
        worst = np.argmax(z, axis=1)
        zmax = z[np.arange(T), worst]
        n_rays = used.sum(axis=1)
        # with two rays a blunder cannot be located: the point is dropped instead
        bad = (zmax > cfg.chi2_ray) & (reason == "")
        removable = bad & (n_rays > cfg.min_rays)
        reason[bad & ~removable] = "inconsistent rays"
        if not removable.any():
            break
        redo = np.nonzero(removable)[0]
        used[redo, worst[removable]] = False
    n_rays = used.sum(axis=1)
    dof = 2 * n_rays - 3
    s0 = np.sqrt(np.sum(np.where(used[..., None], res, 0) ** 2, axis=(1, 2)) / np.maximum(dof, 1)) / cfg.sigma_px
    # covariance with the a-priori precision, scaled up where the point fits worse than expected
    Ninv = np.full((T, 3, 3), np.inf)
    solvable = (n_rays >= 2) & (np.abs(np.linalg.det(N)) > 1e-18)
    Ninv[solvable] = np.linalg.inv(N[solvable])
    reason[(reason == "") & ~solvable] = "fewer than two rays"
    scale = np.where(dof > 0, np.maximum(s0, 1.0), 1.0) ** 2 * cfg.sigma_px ** 2
    cov = Ninv * scale[:, None, None]
    # intersection angle: the widest pair of rays
    if cfg.min_angle_deg > 0:
        d = np.where(used[..., None], dirs, 0.0)
        cosines = np.einsum("tki,tli->tkl", d, d)
        cosines = np.where(used[:, :, None] & used[:, None, :], cosines, 1.0)
        widest = np.degrees(np.arccos(np.clip(cosines.min(axis=(1, 2)), -1, 1)))
        reason[(reason == "") & (widest < cfg.min_angle_deg)] = "rays too nearly parallel"
    reason[(reason == "") & (n_rays < cfg.min_rays)] = "fewer than two rays"
    return {"X": X, "cov": cov, "rays": n_rays, "used": used, "residual_px": res, "sigma0": s0,
            "valid": reason == "", "reason": reason}


def _adjust(cameras, obs, used, X, iterations):
    T, K, _ = obs.shape
    res = np.zeros((T, K, 2))
    for it in range(iterations):
        N = np.zeros((T, 3, 3))
        b = np.zeros((T, 3))
        for k, cam in enumerate(cameras):
            sel = used[:, k]
            if not sel.any():
                continue
            uv, J = project_with_jacobian(cam, X[sel])
            r = obs[sel, k] - uv
            res[sel, k] = r
            N[sel] += np.einsum("nai,naj->nij", J, J)
            b[sel] += np.einsum("nai,na->ni", J, r)
        ok = np.linalg.det(N) > 1e-18
        dX = np.zeros_like(X)
        dX[ok] = np.linalg.solve(N[ok], b[ok][..., None])[..., 0]
        X = X + dX
        if np.max(np.abs(dX), initial=0) < 1e-6:
            break
    # residuals and normal matrix at the solution
    N = np.zeros((T, 3, 3))
    res = np.zeros((T, K, 2))
    for k, cam in enumerate(cameras):
        sel = used[:, k]
        if sel.any():
            uv, J = project_with_jacobian(cam, X[sel])
            res[sel, k] = obs[sel, k] - uv
            N[sel] += np.einsum("nai,naj->nij", J, J)
    return X, N, res
