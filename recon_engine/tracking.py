"""Tracking features through all consecutive images of an arm.

The arm's images are taken in order (1–2, 2–3, …). In each neighbouring pair
the left image's points are matched into the right one along the epipolar
rows. The points of a pair's left image are the tracks that arrived from the
previous pair and fresh Harris features; a fresh feature that falls on an
arriving track merges into it (the chains meet), so a surface point is
followed as far as the images see it. Two tracks that land on the same point
of the next image conflict: the better-correlated one continues, the other is
split off there.

Matching one way leaves the right image's template-worthy skin unmatched
where that skin turns towards the right camera: the left view squeezes it. So
each pair then grows back: the right image's own features that no match
reached are matched into the left image from the matches around them
(region growing with the right image's windows as templates). A match grown
back completes a track that ended on its left point, or starts a track that
goes on from the right image. Then skin that the middle image of three
does not see is grown across it, in the pair of the first and third.

Tracks are returned as (T, K, 2) original pixel coordinates, NaN where a
track has no observation.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from .epipolar import rectify_pair
from .features import blur_sigma, cell_features, harris_features, region_of_interest
from .matching import MatchingConfig, focus_adapted, grow_matches, match_points, reason_counts
from .parallel import cores


@dataclass(frozen=True)
class TrackingConfig:
    spacing: int = 3  # px, minimum distance between Harris features (the density: ~1 mm on the skin at paper scale)
    # cameras coarser than the projected pattern's design (a cheaper rig: about 1 mm pixels on the skin, where the
    # pattern's corners lie 5 mm apart): where the Harris features lie farther apart on the skin than this (mm), a
    # point goes into every cell of about this size without one (features.cell_features, cells of at least 2 px).
    # 0: off. Cheap preset (1000 x 667 px), arm A of tuning seed 41, true calibration: 2.0 gives coverage 42 ->
    # 87 %, RMS 0.131 -> 0.147 mm (with ReconstructionConfig.max_sigma_factor 4), in 4.4 -> 10.7 s under load.
    # At paper scale the features lie 1.8 mm apart; filling 6 px cells there gave +0.9 points of coverage for
    # +0.0013 mm RMS and 1.7x the time, so it is off by default (and would change the tiny and demo presets'
    # measured figures)
    fill_spacing_mm: float = 0.0
    fill_min_texture: float = 0.1  # those points only where the texture reaches this share of the image's 99th pct
    roi_window: int = 15  # px, contrast window of the region of interest
    merge_radius_px: float = 2.0  # a fresh feature this close to an arriving track merges into it
    conflict_radius_px: float = 0.3  # two tracks closer than this in the next image conflict
    # after each pair's matching, the right image's own features that no match reached grow back into the left
    # image from the matches around them: where the skin turns towards the right camera and away from the left
    # one, the left window is the squeezed view of the two, and the right one the better template. Paper scale,
    # coverage of arms A-D 88.2 / 87.6 / 84.5 / 85.4% without, 90.0 / 88.4 / 86.5 / 85.9% with (and without
    # MatchingConfig.sparse_level_fallback, which it makes nearly redundant), in about the same time
    reverse_growing: bool = True
    # growing back only where the left window is at most this stretched against the right one (1: where the right
    # view is the wider one). Where the left view is the wider one the forward matching had the better template
    # already; growing back there too gave arms C / D +0.7 / +0.6 points of coverage (paper scale, at most 0.5 s
    # per arm), but on the tiny preset (2.1 mm pixels) two-ray points up to 3.2 mm off the skin (arm A)
    reverse_max_scale: float = 1.0
    # after pair k+1, k+2 the skin that images k and k+2 see but k+1 does not (hidden behind the subject's arm,
    # say, or seen too obliquely by k+1 to match) is grown from the tracks through all three into pair k, k+2
    # (longer baseline). Paper scale, before eight growing rounds: arm D +0.3 points of coverage, arm C none, for
    # 2 s per arm. With eight rounds (each growing further from the skin the three images share), coverage of arms
    # A-D 93.5 / 92.1 / 90.35 / 89.6% without, 93.6 / 92.3 / 90.6 / 90.5% with, RMS 0.0002-0.0004 mm lower, for
    # 2.5-4 s per arm on a machine that takes 22-25 s for one (about 11%)
    skip_pairs: bool = True
    skip_grow_passes: int = 8  # rounds of that growing (see MatchingConfig.grow_passes)
    matching: MatchingConfig = field(default_factory=MatchingConfig)


def track_images(images: list, cameras: list, depth_bounds, cfg: TrackingConfig | None = None,
                 polygons: list | None = None) -> dict:
    """Tracks through consecutive ``images`` of calibrated ``cameras``.

    Parameters
    ----------
    images : list of K (H, W) arrays
        Grey images in the arm's order: integers at their type's full scale, or floats in 8-bit levels.
    cameras : list of K Camera
        Their IOPs and EOPs.
    depth_bounds : callable or (float, float)
        Nearest and farthest depth (mm) of the subject along the rectified
        viewing direction; a callable gets the ``RectifiedPair``.
    polygons : list of K arrays or None, optional
        User-drawn regions of interest (original pixel coordinates).

    Returns ``{"tracks": (T, K, 2), "ncc": (T, K-1), "pairs": [per-pair figures], "blur_px": (K,) each
    image's blur estimate (``features.blur_sigma``)}``.
    """
    cfg = cfg or TrackingConfig()
    K = len(images)
    with ThreadPoolExecutor(cores(cfg.matching.threads)) as pool:
        blur = list(pool.map(blur_sigma, images))
    # the images' full scale, what least-squares matching counts as saturated: an integer type's largest value;
    # float images are in 8-bit levels (as reconstruct_arm gives a 16-bit image)
    full = max(np.iinfo(im.dtype).max if np.issubdtype(im.dtype, np.integer) else 255.0 for im in images)
    matching = replace(cfg.matching, saturated_level=cfg.matching.saturated_share * full)
    cfg = replace(cfg, matching=matching)

    def pair_cfg(j, k):
        """``cfg`` with the matching settings for images j and k's focus (``matching.focus_adapted``)."""
        return replace(cfg, matching=focus_adapted(cfg.matching, max(blur[j], blur[k])))
    tracks = np.zeros((0, K, 2))
    corr = np.zeros((0, K - 1))
    pairs = []

    def features(pair, side, image, k):
        """Harris features of image k in the pair's rectification (its region of interest, its polygon)."""
        poly = None
        if polygons is not None and polygons[k] is not None:
            poly = pair.to_rectified(side, np.asarray(polygons[k], dtype=float))
        roi = region_of_interest(image, window=cfg.roi_window, polygon=poly)
        xy = harris_features(image, roi, spacing=cfg.spacing)[0]
        cell = fill_cell_px(pair, depth_bounds, roi, len(xy), cfg.fill_spacing_mm)
        if cell:
            xy = np.vstack([xy, cell_features(image, roi, cell, taken=xy, relative_threshold=cfg.fill_min_texture)])
        return xy, roi

    def prepare(k):
        """The rectified pair k, k+1, its left image's region of interest and fresh Harris features."""
        pair = rectify_pair(cameras[k], cameras[k + 1])
        left = pair.resample("left", np.asarray(images[k], dtype=np.float32))
        right = pair.resample("right", np.asarray(images[k + 1], dtype=np.float32))
        fresh, roi = features(pair, "left", left, k)
        return pair, left, right, roi, fresh

    def grow_skip(j, tracks, corr):
        """Pair j, j+2 rectified, grown (``_grow_skip_pair``) and freed, once image j+2 has all its tracks.
        Rectified only then, not with pair j: two such pairs waiting were 0.1 GB of an arm's peak."""
        if not cfg.skip_pairs or j < 0 or j + 2 >= K:
            return tracks, corr
        wide = rectify_pair(cameras[j], cameras[j + 2])
        wide_left = wide.resample("left", np.asarray(images[j], dtype=np.float32))
        wide_right = wide.resample("right", np.asarray(images[j + 2], dtype=np.float32))
        tracks, corr, pairs[j]["skip_grown"] = _grow_skip_pair(j, wide, wide_left, wide_right,
                                                               features(wide, "left", wide_left, j)[0], tracks,
                                                               corr, pair_cfg(j, j + 2))
        return tracks, corr

    # with more than one thread the next pair is prepared on another (OpenCV releases the GIL) while this one is
    # matched: it fills the matching's single-threaded stretches. Pair k-1 grows back with image k's features,
    # prepared with pair k, before pair k's matching (its new tracks go on from image k); pair k-2, k grows once
    # image k has all its tracks
    back = None
    for k, prepared in enumerate(_in_order(prepare, K - 1, ahead=cores(cfg.matching.threads) > 1)):
        pair, fresh = prepared[0], prepared[4]
        if back is not None:
            # image k's features in pair k-1's rectification (the right image)
            features_k = back[0].to_rectified("right", pair.to_original("left", fresh))
            tracks, corr, pairs[k - 1]["grown_back"] = _grow_back(k - 1, *back, features_k, tracks, corr,
                                                                  pair_cfg(k - 1, k))
            back = None  # pair k-1's images are freed before pair k is matched
        tracks, corr = grow_skip(k - 2, tracks, corr)
        here = pair_cfg(k, k + 1)
        tracks, corr, figures, back = _track_pair(k, *prepared, tracks, corr, depth_bounds, here)
        figures["blur_px"] = round(max(blur[k], blur[k + 1]), 3)
        figures["out_of_focus"] = here.matching is not cfg.matching  # matched with the blurred_* settings
        pairs.append(figures)
    if back is not None:
        # the last image has no pair of its own: its features in the last pair's rectification
        tracks, corr, pairs[-1]["grown_back"] = _grow_back(K - 2, *back, features(back[0], "right", back[2], K - 1)[0],
                                                           tracks, corr, pair_cfg(K - 2, K - 1))
    tracks, corr = grow_skip(K - 3, tracks, corr)
    return {"tracks": tracks, "ncc": corr, "pairs": pairs, "blur_px": np.array(blur)}


def track_windows(tracks: np.ndarray, blur_px, cfg: MatchingConfig) -> np.ndarray:
    """Each track's least-squares window (px): the root mean square of the windows of the image pairs that matched
    it (``focus_adapted``: an out-of-focus pair matches with ``blurred_lsm_window``).

    ``tracks`` (T, K, 2) as :func:`track_images` returns them, ``blur_px`` (K,) its images' blur estimates. A
    track's pairs are its consecutive observations, one image apart or two (a skip pair). Returns (T,) px.
    """
    seen = np.isfinite(np.asarray(tracks)[:, :, 0])
    K = seen.shape[1]
    total, count = np.zeros(len(seen)), np.zeros(len(seen))
    for j in range(K - 1):
        for k in (j + 1, j + 2):
            if k >= K:
                continue
            used = seen[:, j] & seen[:, k] & ((k == j + 1) | ~seen[:, j + 1])
            m = focus_adapted(cfg, max(float(blur_px[j]), float(blur_px[k])))
            total[used] += float(m.lsm_window or m.window) ** 2
            count[used] += 1
    fallback = float(cfg.lsm_window or cfg.window)
    return np.where(count > 0, np.sqrt(total / np.maximum(count, 1)), fallback)


def fill_cell_px(pair, depth_bounds, roi: np.ndarray, n_features: int, spacing_mm: float) -> int:
    """The cell (px) of the points that fill the gaps between the features, or 0 where none are needed.

    The features' typical spacing on the skin is the region of interest's
    area per feature (px), times the size of a rectified pixel at the
    subject's mid depth (mm). Where it exceeds ``spacing_mm``, cells of about
    ``spacing_mm`` on the skin, at least 2 px.
    """
    if spacing_mm <= 0 or n_features == 0:
        return 0
    d0, d1 = depth_bounds(pair) if callable(depth_bounds) else depth_bounds
    pixel_mm = 0.5 * (d0 + d1) / pair.f
    spacing = np.sqrt(roi.sum() / n_features) * pixel_mm
    return max(2, int(round(spacing_mm / pixel_mm))) if spacing > spacing_mm else 0


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
    the matches (new arrays), the pair's figures for the report, and what
    growing back needs of the pair (None when it is off or has no seeds).
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
    xy_r, idx, rho = _drop_conflicts(xy_r, idx, rho, cfg.conflict_radius_px)
    tracks[ids[idx], k + 1] = pair.to_original("right", xy_r)
    corr[ids[idx], k] = rho
    figures = {"left": k, "right": k + 1, "roi_fraction": float(roi.mean()), "fresh_features": int(len(fresh)),
               "arriving_tracks": int(len(arriving)), "matched": int(len(idx)),
               "rejected": reason_counts(m["reason"][~ok])}
    back = (pair, left, right, xy, ids, idx, xy_r) if cfg.reverse_growing and len(idx) >= 3 else None
    return tracks, corr, figures, back


def _grow_skip_pair(k, pair, left, right, fresh, tracks, corr, cfg):
    """Pair k, k+2: left features that no track takes into image k+1 or k+2, grown from the tracks through both.

    The new matches start tracks of images k and k+2 (or complete a track
    of image k on whose point they land). Returns the tracks and
    correlations (new arrays) and how many matches grew.
    """
    at_k = np.isfinite(tracks[:, k, 0])
    both = np.nonzero(at_k & np.isfinite(tracks[:, k + 2, 0]))[0]
    onward = np.nonzero(at_k & (np.isfinite(tracks[:, k + 1, 0]) | np.isfinite(tracks[:, k + 2, 0])))[0]
    if len(both) < 3 or len(fresh) == 0:
        return tracks, corr, 0
    seeds = pair.to_rectified("left", tracks[both, k])
    seeds_right = pair.to_rectified("right", tracks[both, k + 2])
    d, _ = cKDTree(pair.to_rectified("left", tracks[onward, k])).query(fresh, k=1)
    cand = fresh[d > cfg.merge_radius_px]
    if len(cand) == 0:
        return tracks, corr, 0
    g = grow_matches(left, right, np.concatenate([seeds, cand]),
                     np.concatenate([seeds_right, np.full((len(cand), 2), np.nan)]),
                     replace(cfg.matching, grow_passes=cfg.skip_grow_passes))
    won = g["valid"][len(seeds):]
    new_left, new_right, rho = cand[won], g["xy"][len(seeds):][won], g["ncc"][len(seeds):][won]
    # a match onto a point of image k + 2 that a track already holds is a conflict
    at_k2 = np.isfinite(tracks[:, k + 2, 0])
    if at_k2.any() and len(new_right):
        keep = cKDTree(pair.to_rectified("right", tracks[at_k2, k + 2])).query(new_right, k=1)[0] > cfg.merge_radius_px
        new_left, new_right, rho = new_left[keep], new_right[keep], rho[keep]
    new_left, new_right, rho = _drop_conflicts(new_left, new_right, rho, cfg.conflict_radius_px)
    if len(new_left) == 0:
        return tracks, corr, 0
    # tracks that end in image k: a match that lands on one's point completes it. The correlation of a k, k+2
    # match stands in the first gap's column (no pair of its own)
    ending = np.nonzero(at_k & ~np.isfinite(tracks[:, k + 1, 0]) & ~at_k2)[0]
    tracks, corr = _attach(tracks, corr, pair, k, k + 2, new_left, new_right, rho,
                           pair.to_rectified("left", tracks[ending, k]), ending, cfg)
    return tracks, corr, int(len(new_left))


def _drop_conflicts(xy_a, xy_b, rho, radius):
    """Of two matches whose points ``xy_a`` are closer than ``radius``, the better-correlated (``rho``) one stays.

    ``xy_b`` (their other points, or any array along them) is filtered alike."""
    if len(xy_a) > 1:
        close = cKDTree(xy_a).query_pairs(radius, output_type="ndarray")
        if len(close):
            keep = np.ones(len(xy_a), bool)
            keep[np.where(rho[close[:, 0]] >= rho[close[:, 1]], close[:, 1], close[:, 0])] = False
            return xy_a[keep], xy_b[keep], rho[keep]
    return xy_a, xy_b, rho


def _landing(track_xy, xy, track_ids, radius):
    """For each point of ``xy``, the id of the track (of ``track_ids`` at ``track_xy``) it lands on, else -1; one
    point per track (the first)."""
    target = np.full(len(xy), -1)
    if len(track_ids) and len(xy):
        dist, j = cKDTree(track_xy).query(xy, k=1)
        hit = np.nonzero(dist <= radius)[0]
        _, first = np.unique(track_ids[j[hit]], return_index=True)
        target[hit[first]] = track_ids[j[hit[first]]]
    return target


def _attach(tracks, corr, pair, k, k_other, xy_k, xy_other, rho, ending_xy, ending_ids, cfg):
    """Matches of image k (``xy_k``, the pair's left image) and image ``k_other`` (``xy_other``, its right one),
    rectified in ``pair``, into the tracks.

    A match that lands on the image-k point ``ending_xy`` of a track of
    ``ending_ids`` (as close as two conflicting tracks) completes it; the
    others start new tracks. Returns the tracks and correlations (new arrays).
    """
    target = _landing(ending_xy, xy_k, ending_ids, cfg.conflict_radius_px)
    start = target < 0
    K = tracks.shape[1]
    new = np.full((int(start.sum()), K, 2), np.nan)
    new[:, k] = pair.to_original("left", xy_k[start])
    target[start] = np.arange(len(tracks), len(tracks) + len(new))
    tracks = np.concatenate([tracks, new])
    corr = np.concatenate([corr, np.full((len(new), K - 1), np.nan)])
    tracks[target, k_other] = pair.to_original("right", xy_other)
    corr[target, k] = rho
    return tracks, corr


def _grow_back(k, pair, left, right, xy, ids, idx, xy_r, fresh_right, tracks, corr, cfg):
    """Right-image features of pair k that no match reached, grown back into its left image from the matches.

    A match that lands on a left point of a track without an observation in
    the right image completes that track; the others start new tracks.
    Returns the tracks and correlations (new arrays) and how many matches grew back.
    """
    if len(fresh_right) == 0:
        return tracks, corr, 0
    d, _ = cKDTree(xy_r).query(fresh_right, k=1)
    cand = fresh_right[d > cfg.merge_radius_px]
    if len(cand) == 0:
        return tracks, corr, 0
    # the pair reversed: the right image's points are the templates, the matches so far the seeds
    lo = cfg.matching.grow_scale_range[0]
    g = grow_matches(right, left, np.concatenate([xy_r, cand]),
                     np.concatenate([xy[idx], np.full((len(cand), 2), np.nan)]),
                     replace(cfg.matching, grow_scale_range=(lo, cfg.reverse_max_scale)))
    won = g["valid"][len(xy_r):]
    back_right, back_left, rho = cand[won], g["xy"][len(xy_r):][won], g["ncc"][len(xy_r):][won]
    # a match onto a left point that already has its right point, or onto another grown match, is a conflict
    keep = cKDTree(xy[idx]).query(back_left, k=1)[0] > cfg.merge_radius_px
    back_left, back_right, rho = _drop_conflicts(back_left[keep], back_right[keep], rho[keep], cfg.conflict_radius_px)
    if len(back_left) == 0:
        return tracks, corr, 0
    # the left points of this pair's tracks that found no right point: a grown match that lands on one completes it
    unmatched = np.setdiff1d(np.arange(len(xy)), idx)
    tracks, corr = _attach(tracks, corr, pair, k, k + 1, back_left, back_right, rho, xy[unmatched], ids[unmatched],
                           cfg)
    return tracks, corr, int(len(back_left))
