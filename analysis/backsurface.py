"""The back as a depth map, its horizontal profiles and the line of symmetry.

Rasterstereography's view of the back: in the patient frame, the posterior
coordinate ``y`` of the back's skin over a regular grid of ``x`` (left) and
``z`` (up), smoothed. A horizontal section is one row of the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter, maximum_filter

from .config import IndicesConfig


@dataclass
class DepthMap:
    """``depth[i, j]``: posterior coordinate (mm) of the back at ``z[i]``, ``x[j]`` (patient frame); NaN: no skin."""

    x: np.ndarray
    z: np.ndarray
    depth: np.ndarray

    def row(self, zq: float) -> np.ndarray:
        """The section at height ``zq`` (linear between rows)."""
        i = np.interp(zq, self.z, np.arange(len(self.z)))
        i0 = int(np.clip(np.floor(i), 0, len(self.z) - 1))
        i1 = min(i0 + 1, len(self.z) - 1)
        f = i - i0
        return (1 - f) * self.depth[i0] + f * self.depth[i1]

    def at(self, xq, zq, max_gap_mm: float | None = None) -> float:
        """The depth (mm) at ``xq``, ``zq``; with ``max_gap_mm``, read across missing cells up to that wide
        (:func:`depth_across_gap`), else NaN beside any missing cell."""
        if max_gap_mm is not None:
            return depth_across_gap(self.x, self.row(zq), xq, max_gap_mm)
        return float(np.interp(xq, self.x, self.row(zq), left=np.nan, right=np.nan))


def depth_across_gap(x: np.ndarray, row: np.ndarray, xq: float, max_gap_mm: float) -> float:
    """The depth (mm) of one row of the depth map at ``xq`` (mm), linear between the nearest cells with a value
    either side when they lie at most ``max_gap_mm`` apart; NaN beyond the row's values or across a wider hole."""
    ok = np.isfinite(row)
    xf, rf = x[ok], row[ok]
    j = int(np.searchsorted(xf, xq))
    if j < len(xf) and xf[j] == xq:
        return float(rf[j])
    if j == 0 or j == len(xf) or xf[j] - xf[j - 1] > max_gap_mm + 1e-9:
        return float("nan")
    return float(np.interp(xq, xf[j - 1:j + 1], rf[j - 1:j + 1]))


def back_points(P: np.ndarray, N: np.ndarray, cfg: IndicesConfig) -> np.ndarray:
    """Mask of the points (patient frame) on the back: normal within ``back_normal_deg`` of posterior."""
    return N[:, 1] >= np.cos(np.radians(cfg.back_normal_deg))


def depth_map(P: np.ndarray, N: np.ndarray, cfg: IndicesConfig, half_width_mm: float = 220.0) -> DepthMap:
    """The back's depth map from points ``P`` and outward normals ``N`` in the patient frame.

    Cell value: the mean posterior coordinate of the back points in it, then a
    normalized Gaussian smoothing of ``cfg.smooth_mm`` (fills small holes);
    cells far from any point stay NaN.
    """
    g = cfg.grid_mm
    B = P[back_points(P, N, cfg)]
    xs = np.arange(-half_width_mm, half_width_mm + g / 2, g)
    zs = np.arange(np.floor(B[:, 2].min() / g) * g, B[:, 2].max() + g, g)
    ix = np.round((B[:, 0] - xs[0]) / g).astype(int)
    iz = np.round((B[:, 2] - zs[0]) / g).astype(int)
    ok = (ix >= 0) & (ix < len(xs)) & (iz >= 0) & (iz < len(zs))
    # keep the most posterior layer of each cell only: skin seen through a gap (the front of a hand, a fold
    # of the belly facing backwards) lies in front of the back and is not the back
    iz, ix, B = iz[ok], ix[ok], B[ok]
    top = np.full((len(zs), len(xs)), -np.inf)
    np.maximum.at(top, (iz, ix), B[:, 1])
    # and as far as the smoothing reaches (3 sigma): an empty cell beside the back must not take the value of
    # skin far in front of it (the sides of forearms crossed before the chest face partly backwards; they moved
    # the back's midline by 14 mm and its slope there to 56 deg on a body of seed 200). Skin whose normal is within
    # back_normal_deg of posterior rises by at most tan(back_normal_deg) per mm across: 102 mm over 3 sigma at
    # 80 deg and 18 mm, so the back's own steep flanks stay
    sigma = cfg.smooth_mm / g
    reach = int(np.ceil(3 * sigma))
    rise = 3 * cfg.smooth_mm * np.tan(np.radians(cfg.back_normal_deg))
    envelope = maximum_filter(top, size=2 * reach + 1, mode="constant", cval=-np.inf)
    layer = (B[:, 1] >= top[iz, ix] - cfg.layer_mm) & (B[:, 1] >= envelope[iz, ix] - rise - cfg.layer_mm)
    iz, ix, B = iz[layer], ix[layer], B[layer]
    s = np.zeros((len(zs), len(xs)))
    c = np.zeros_like(s)
    np.add.at(s, (iz, ix), B[:, 1])
    np.add.at(c, (iz, ix), 1.0)
    ss = gaussian_filter(s, sigma, mode="constant")
    cs = gaussian_filter(c, sigma, mode="constant")
    support = gaussian_filter((c > 0).astype(float), sigma, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(support > 0.35, ss / cs, np.nan)
    return DepthMap(xs, zs, depth)


def slope_at(x: np.ndarray, profile: np.ndarray, x0: float, half_width: float) -> float:
    """Least-squares slope d(depth)/dx of the profile over ``x0 ± half_width`` (mm/mm)."""
    sel = (np.abs(x - x0) <= half_width) & np.isfinite(profile)
    if sel.sum() < 3:
        return np.nan
    xx = x[sel] - x0
    yy = profile[sel]
    A = np.column_stack([xx, np.ones_like(xx)])
    return float(np.linalg.lstsq(A, yy, rcond=None)[0][0])


def prominence_difference(x: np.ndarray, profile: np.ndarray, x0: float, u_range: tuple,
                          min_share: float = 0.5) -> tuple[float, float]:
    """The rib hump of one horizontal profile: ``(height_mm, span_mm)``.

    ``profile`` is the back's depth (posterior coordinate, mm) along ``x``
    (mm, towards the patient's left); ``x0`` the symmetry point. On either
    side, the highest point of the back between ``u_range[0]`` and
    ``u_range[1]`` mm from ``x0`` (the paraspinal prominence); the height is the
    right one's minus the left one's (+: the right side stands out), which is
    the gap under a level resting horizontally on the higher side, measured
    at the lower side's prominence. ``span_mm`` is the distance across between
    the two prominences (the Scoliometer's chord: ``atan(height / span)``).

    A prominence is a maximum, so it hardly moves when ``x0`` is a few
    millimetres off, unlike the height difference at two points symmetric
    about ``x0`` (which changes by twice the back's slope there per
    millimetre). NaN where less than ``min_share`` of either side's
    distances have a depth.
    """
    x = np.asarray(x, float)
    profile = np.asarray(profile, float)
    lo, hi = u_range
    ok = np.isfinite(profile)
    right = ok & (x <= x0 - lo) & (x >= x0 - hi)
    left = ok & (x >= x0 + lo) & (x <= x0 + hi)
    step = float(np.median(np.diff(x))) if len(x) > 1 else 1.0
    need = min_share * (hi - lo) / step
    if right.sum() < need or left.sum() < need:
        return float("nan"), float("nan")
    i = np.nonzero(right)[0][np.argmax(profile[right])]
    j = np.nonzero(left)[0][np.argmax(profile[left])]
    return float(profile[i] - profile[j]), float(x[j] - x[i])


def central_extent(xs: np.ndarray, gap_mm: float, around: float = 0.0) -> tuple[float, float]:
    """The run of sorted coordinates ``xs`` without gaps wider than ``gap_mm`` that holds ``around`` (or is nearest)."""
    if len(xs) == 0:
        return np.nan, np.nan
    s = np.sort(xs)
    breaks = np.nonzero(np.diff(s) > gap_mm)[0]
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [len(s) - 1]])
    best, best_d = 0, np.inf
    for k, (a, b) in enumerate(zip(starts, ends)):
        d = 0.0 if s[a] <= around <= s[b] else min(abs(s[a] - around), abs(s[b] - around))
        if d < best_d:
            best, best_d = k, d
    return float(s[starts[best]]), float(s[ends[best]])


def symmetry_costs(x: np.ndarray, rows: np.ndarray, centres: np.ndarray, window_mm: float, search_mm: float,
                   step_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The mirror misfit of every row at every candidate symmetry point: ``(offsets, cost)``.

    ``rows`` (n, len(x)): horizontal profiles of the depth map (mm, NaN: no skin) on the regular grid ``x``;
    ``centres`` (n,): where each row's search is centred (mm). For a candidate ``x0`` the row's right half is
    compared with its left half mirrored after removing a linear tilt (a turned symmetric profile is, to
    first order, symmetric plus a tilt): ``cost[k, c]`` is the RMS residual (mm) of
    ``d(x0+u) - d(x0-u) = 2·a·u`` for ``0 < u <= window_mm``, about ``x0 = centres[k] + offsets[c]``
    (``offsets`` every ``step_mm`` within ``±search_mm``); ``inf`` where less than 80 % of the window's
    distances have skin on both sides.
    """
    x = np.asarray(x, float)
    rows = np.array(rows, dtype=float)
    for r in rows:  # holes inside a row are bridged linearly; beyond its ends, no skin
        good = np.isfinite(r)
        if 2 <= good.sum() < len(r):
            r[:] = np.interp(x, x[good], r[good], left=np.nan, right=np.nan)
    g = float(x[1] - x[0])
    u = np.arange(g, window_mm + 1e-9, g)
    offsets = np.arange(-search_mm, search_mm + 1e-9, step_mm)
    cand = np.asarray(centres, float)[:, None] + offsets[None, :]  # (n, c)

    def sample(q):  # rows at positions q (n, c, u), linear on the regular grid; NaN outside
        p = (q - x[0]) / g
        i0 = np.floor(p).astype(int)
        f = p - i0
        inside = (i0 >= 0) & (i0 < len(x) - 1)
        i0 = np.clip(i0, 0, len(x) - 2)
        r = np.arange(rows.shape[0])[:, None, None]
        v = (1 - f) * rows[r, i0] + f * rows[r, i0 + 1]
        return np.where(inside, v, np.nan)

    with np.errstate(invalid="ignore"):
        diff = sample(cand[:, :, None] + u) - sample(cand[:, :, None] - u)
    ok = np.isfinite(diff)
    uu = np.where(ok, u, 0.0)
    dd = np.where(ok, diff, 0.0)
    n_ok = ok.sum(axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = (dd * uu).sum(axis=2) / (uu * uu).sum(axis=2)
        res = np.where(ok, dd - slope[..., None] * uu, 0.0)
        cost = np.sqrt((res ** 2).sum(axis=2) / n_ok)
    cost = np.where((n_ok >= 0.8 * len(u)) & np.isfinite(cost), cost, np.inf)
    return offsets, cost


def smoothest_path(cost: np.ndarray, offsets: np.ndarray, centres: np.ndarray, penalty: float) -> np.ndarray:
    """The line through the rows that minimizes the misfit plus ``penalty`` times its squared steps (mm).

    ``cost`` (n, c) from :func:`symmetry_costs`. Dynamic programming (Viterbi) over the rows: each row's
    candidate positions ``centres[k] + offsets``; a step of ``d`` mm between neighbouring rows costs
    ``penalty · d²``. A row with no finite cost adds nothing, so the line runs on through it from the rows
    around; it is NaN in the result. Returns each row's position (mm), refined by a parabola through the
    chosen candidate's cost and its neighbours'.
    """
    n, c = cost.shape
    pos = np.asarray(centres, float)[:, None] + offsets[None, :]
    finite = np.isfinite(cost)
    seen = finite.any(axis=1)
    # relative to each row's best: how much worse a candidate fits, not the row's own roughness; a candidate
    # the row cannot read is out of bounds unless the row reads none
    best = np.min(np.where(finite, cost, np.inf), axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        base = np.where(finite, cost - best, np.where(seen[:, None], 1e6, 0.0))
    total = base[0].copy()
    back = np.zeros((n, c), dtype=int)
    for k in range(1, n):
        step = pos[k][:, None] - pos[k - 1][None, :]  # (c here, c before)
        t = total[None, :] + penalty * step ** 2
        back[k] = np.argmin(t, axis=1)
        total = base[k] + t[np.arange(c), back[k]]
    path = np.zeros(n, dtype=int)
    path[-1] = int(np.argmin(total))
    for k in range(n - 1, 0, -1):
        path[k - 1] = back[k, path[k]]
    out = pos[np.arange(n), path].copy()
    k = np.arange(n)
    inner = (path > 0) & (path < c - 1)
    c0 = np.where(inner, cost[k, np.clip(path - 1, 0, c - 1)], np.nan)
    c1 = cost[k, path]
    c2 = np.where(inner, cost[k, np.clip(path + 1, 0, c - 1)], np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        den = c0 - 2 * c1 + c2
        shift = np.where(np.isfinite(den) & (den > 0), 0.5 * (c0 - c2) / den, 0.0)
    step_mm = offsets[1] - offsets[0] if len(offsets) > 1 else 1.0
    out += np.clip(shift, -0.5, 0.5) * step_mm
    out[~seen | ~np.isfinite(c1)] = np.nan
    return out
