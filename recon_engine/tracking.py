"""Tracking features through all consecutive images of an arm.

The arm's images are taken in order (1–2, 2–3, …). In each neighbouring pair
the left image's points are matched into the right one along the epipolar
rows. The points of a pair's left image are the tracks that arrived from the
previous pair and fresh Harris features; a fresh feature that falls on an
arriving track merges into it (the chains meet), so a surface point is
followed as far as the images see it. Two tracks that land on the same point
of the next image conflict: the better-correlated one continues, the other is
split off there.

Tracks are returned as (T, K, 2) original pixel coordinates, NaN where a
track has no observation.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .epipolar import rectify_pair
from .features import harris_features, region_of_interest
from .matching import MatchingConfig, match_points, reason_counts
from .parallel import cores


@dataclass(frozen=True)
class TrackingConfig:
    spacing: int = 3  # px, minimum distance between Harris features (the density: ~1 mm on the skin at paper scale)
    roi_window: int = 15  # px, contrast window of the region of interest
    merge_radius_px: float = 2.0  # a fresh feature this close to an arriving track merges into it
    conflict_radius_px: float = 0.3  # two tracks closer than this in the next image conflict
    matching: MatchingConfig = field(default_factory=MatchingConfig)


def track_images(images: list, cameras: list, depth_bounds, cfg: TrackingConfig | None = None,
                 polygons: list | None = None) -> dict:
    """Tracks through consecutive ``images`` of calibrated ``cameras``.

    Parameters
    ----------
    images : list of K (H, W) arrays
        Grey images in the arm's order.
    cameras : list of K Camera
        Their IOPs and EOPs.
    depth_bounds : callable or (float, float)
        Nearest and farthest depth (mm) of the subject along the rectified
        viewing direction; a callable gets the ``RectifiedPair``.
    polygons : list of K arrays or None, optional
        User-drawn regions of interest (original pixel coordinates).

    Returns ``{"tracks": (T, K, 2), "ncc": (T, K-1), "pairs": [per-pair figures]}``.
    """
    cfg = cfg or TrackingConfig()
    K = len(images)
    tracks = np.zeros((0, K, 2))
    corr = np.zeros((0, K - 1))
    pairs = []

    def prepare(k):
        """The rectified pair k, k+1, its left image's region of interest and fresh Harris features."""
        pair = rectify_pair(cameras[k], cameras[k + 1])
        left = pair.resample("left", np.asarray(images[k], dtype=np.float32))
        right = pair.resample("right", np.asarray(images[k + 1], dtype=np.float32))
        poly = None
        if polygons is not None and polygons[k] is not None:
            poly = pair.to_rectified("left", np.asarray(polygons[k], dtype=float))
        roi = region_of_interest(left, window=cfg.roi_window, polygon=poly)
        fresh, _ = harris_features(left, roi, spacing=cfg.spacing)
        return pair, left, right, roi, fresh

    # with more than one thread the next pair is prepared on another (OpenCV releases the GIL) while this one is
    # matched: it fills the matching's single-threaded stretches
    for k, prepared in enumerate(_in_order(prepare, K - 1, ahead=cores(cfg.matching.threads) > 1)):
        tracks, corr, figures = _track_pair(k, *prepared, tracks, corr, depth_bounds, cfg)
        pairs.append(figures)
    return {"tracks": tracks, "ncc": corr, "pairs": pairs}


def _in_order(fn, n: int, ahead: bool):
    """``fn(0)``, …, ``fn(n - 1)`` in order; with ``ahead``, each next one computed on another thread meanwhile.

    Up to three results are alive at once: the one in use, the next one, and
    the one after it being computed.
    """
    if not ahead:
        for k in range(n):
            yield fn(k)
        return
    with ThreadPoolExecutor(1) as pool:
        pending = pool.submit(fn, 0) if n else None
        for k in range(n):
            ready = pending.result()
            if k + 1 < n:
                pending = pool.submit(fn, k + 1)
            yield ready


def _track_pair(k, pair, left, right, roi, fresh, tracks, corr, depth_bounds, cfg):
    """Matches pair k's arriving tracks and fresh features into its right image.

    Returns the tracks and correlations grown by the fresh features and
    the matches (new arrays), and the pair's figures for the report.
    """
    K = tracks.shape[1]
    arriving = np.nonzero(np.isfinite(tracks[:, k, 0]))[0]
    xy_arr = pair.to_rectified("left", tracks[arriving, k]) if len(arriving) else np.zeros((0, 2))
    if len(arriving) and len(fresh):
        d, _ = cKDTree(xy_arr).query(fresh, k=1)
        fresh = fresh[d > cfg.merge_radius_px]
    # new tracks for the fresh features
    new = np.full((len(fresh), K, 2), np.nan)
    new[:, k] = pair.to_original("left", fresh)
    tracks = np.concatenate([tracks, new])
    corr = np.concatenate([corr, np.full((len(fresh), K - 1), np.nan)])
    ids = np.concatenate([arriving, np.arange(len(tracks) - len(fresh), len(tracks))])
    xy = np.concatenate([xy_arr, fresh])
    d0, d1 = depth_bounds(pair) if callable(depth_bounds) else depth_bounds
    m = match_points(left, right, xy, pair.disparity_range(d0, d1), cfg.matching)
    ok = m["valid"]
    idx = np.nonzero(ok)[0]
    xy_r = m["xy"][ok]
    rho = m["ncc"][ok]
    # conflicts: two tracks on one point of the right image; the better one continues
    if len(xy_r) > 1:
        pairs_close = cKDTree(xy_r).query_pairs(cfg.conflict_radius_px, output_type="ndarray")
        if len(pairs_close):
            loser = np.where(rho[pairs_close[:, 0]] >= rho[pairs_close[:, 1]], pairs_close[:, 1], pairs_close[:, 0])
            keep = np.ones(len(xy_r), bool)
            keep[loser] = False
            idx, xy_r, rho = idx[keep], xy_r[keep], rho[keep]
    tracks[ids[idx], k + 1] = pair.to_original("right", xy_r)
    corr[ids[idx], k] = rho
    return tracks, corr, {"left": k, "right": k + 1, "roi_fraction": float(roi.mean()),
                          "fresh_features": int(len(fresh)), "arriving_tracks": int(len(arriving)),
                          "matched": int(len(idx)), "rejected": reason_counts(m["reason"][~ok])}
