"""Normalized cross-correlation matching along the epipolar rows of a rectified pair.

For each point of the left image, a window around it is compared with every
window of the right image along its row (and a few rows either side, to
absorb calibration errors) over a disparity range. Two stages keep the long
search honest and short:

1. a sparse subset of the points, with a larger window for distinctiveness,
   searches the whole disparity range that the rig geometry and the
   subject's depth bounds allow (in the image pyramid's first level, each
   peak then found again at full resolution); matches that disagree with
   their neighbours are dropped;
2. every point searches a short range around the disparity its matched
   neighbours predict, with the right window stretched and sheared as
   their disparity plane's gradient predicts;
3. region growing: the points still unmatched search again where the
   points matched so far predict their disparity, and the stretch and
   shear of the right window (the local disparity plane's gradient), so
   matching follows the skin where it turns away from the cameras and its
   two views foreshorten it differently.

Each match has a subpixel peak (parabola fits across columns and rows), a
minimum correlation, a uniqueness test (second peak against the first) and a
left-right consistency check (the right point matched back must land on the
left point), then least-squares matching (affine along the row, with a
radiometric gain and offset) refines it. Where the right view squeezes the
skin, each of its pixels averages several of the template's: least-squares
matching blurs the template along its rows to that detail first.

The correlation search and least-squares matching of each point run in
compiled loops (``kernels``); this module decides what is searched where.
All coordinates are rectified pixels (x = column, y = row).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .kernels import lsm_points, ncc_points
from .parallel import cores


@dataclass(frozen=True)
class MatchingConfig:
    # windows of a few projector pixels: larger ones lose correlation to the
    # different foreshortening of the skin in converging views
    window: int = 7  # px, side of the correlation window (about 2.5 projector pixels)
    sparse_window: int = 13  # px, window of the full-range search of stage 1
    # px, one stage-1 point per square of this side. Denser seeds reach more of the steep skin and the narrow
    # overlaps: paper scale, coverage of arms A-D 86.8 / 86.5 / 81.3 / 84.6% with 24 px, 88.2 / 87.6 / 84.5 / 85.4%
    # with 12 px (about 2 s more per arm); tiny preset, the weak overlap B-C 20 point-patch pairs in the
    # registration with 24 px (its minimum), 111 with 12. Since twelve growing rounds reach the steep skin from
    # fewer seeds: 16 px, A-D 93.0 / 90.6 / 89.2 / 88.5% against 92.9 / 91.0 / 89.3 / 88.6% with 12 px, arm D 1.0 s
    # faster (13.6 against 14.7 s, warm)
    anchor_spacing: int = 16
    band: int = 2  # rows searched either side of the epipolar row (stage 2; stage 1 stays on the row)
    min_ncc: float = 0.6  # weaker peaks are not matches (least-squares matching checks again)
    sparse_min_ncc: float = 0.7
    # pyramid level of stage 1's long search (halvings; 0: full resolution), its peaks then found again at full
    # resolution
    sparse_level: int = 1
    # px, the long search uses the pyramid only for ranges at least this long either side (paper scale: about
    # 400 px; the tiny preset's 480 x 320 px images, whose pattern halving blurs away: under 100 px)
    sparse_level_min_radius: int = 150
    # seeds the pyramid's search rejects search again at full resolution. Paper scale, with growing back
    # (tracking): arm C +0.1 points of coverage for 3.6 s, arm D +0.7 for 3.5 s (+0.2-0.8 without growing back)
    sparse_level_fallback: bool = False
    uniqueness: float = 0.9  # the second peak must stay below this fraction of the first
    dense_radius: int = 6  # px, stage-2 search either side of the predicted disparity
    # stage 2 tries the stretch and shear of the right window that its anchors' disparity plane predicts (the
    # plane's gradient), then these fixed stretches along the row for the points not matched well. Paper scale,
    # coverage of arms A-D: fixed (1.0, 0.8, 1.25) only 85.8 / 85.9 / 81.3 / 83.6%, 1.77 tries per point on arm C;
    # predicted, then (0.8, 1.25): 86.8 / 86.5 / 81.3 / 84.6%, 1.72 tries; predicted only: the same coverage in one
    # try, and predicted, then 1.0: A 86.8, C 81.6%, but with either the tiny preset's weak overlap B-C lost its
    # point-patch pairs (the torso's RMS 0.56 and 0.82 mm against 0.53): the tiny preset's registration flips with
    # small changes of the surfaces
    predicted_shape: bool = True
    scales: tuple = (0.8, 1.25)
    retry_below_ncc: float = 0.85  # points matched less well than this with one stretch try the next
    neighbours: int = 8  # stage-1 matches that predict a point's disparity
    neighbour_tolerance_px: float = 3.0  # stage-1 match dropped when further from its neighbours' median
    lr_tolerance_px: float = 0.5  # left-right check
    refine: bool = True  # least-squares matching after the correlation peak
    # px, window of least-squares matching (0: the correlation window of the stage). The stretch and shear are
    # estimated, so a window larger than the correlation's holds more of the pattern without losing the fit:
    # paper scale, arm A, true calibration: 7 px: RMS 0.048 mm; 9: 0.036 mm; 11: 0.033 mm (1.5-2.5 s more per arm)
    lsm_window: int = 9
    min_lsm_rho: float = 0.8  # least-squares matching must end at least this correlated
    max_lsm_sigma_px: float = 0.1  # and this precise (x shift, 1-sigma)
    # px, an image's own blur (Gaussian sigma in its pixels: footprint, optics, resampling, light diffused in the
    # skin); least-squares matching blurs the template to a squeezed right window's detail by this (see
    # least_squares_refine; 0: off). Paper scale, 4 growing rounds, coverage / RMS of arms B, C, D: off 88.3 / 86.5
    # / 86.1%, 0.039 / 0.038 / 0.037 mm; 0.6 px: C 87.2%, 0.036 mm; 0.9 px: 89.4 / 87.4 / 87.0%, 0.032 / 0.034 /
    # 0.032 mm; 1.2 px: C 87.5%, 0.035 mm; 1.5 px: C 87.2%, 0.042 mm. More than the images hold misleads it: the
    # tiny preset's pixels are 6 times the paper's, the light diffused in the skin a sixth of a pixel there, and
    # 0.9 px put a two-ray point 5.8 mm off the skin of its arm B (0.7 px: 2.8 mm; off: 2.1 mm). A rig's real
    # blur is not known this well: 0.7 px (paper scale, 12 rounds: arms C / D 89.3 / 88.6% against 89.4 / 88.8%
    # with 0.9, RMS 0.035 / 0.033 mm against 0.034 / 0.032). Choosing it per pair by least-squares matching's
    # median precision on a sample of squeezed windows is no guard: that precision was best at 0.9 px on the tiny
    # preset too (the three pairs of arms A, B with enough squeezed windows), and arm D at paper scale came out as
    # with 0.9 px
    lsm_antialias_px: float = 0.7
    # an image pair whose blurrier image reads above this (features.blur_sigma, px) is out of focus: its
    # least-squares matching takes larger windows (more of the blurred pattern's weaker gradients) and blurs the
    # template by the pair's own blur. Tuned on seed 35, arm A, paper scale, true calibration: in focus the images
    # read 0.58-0.74 px, the cameras focused 35 cm short at f/4 0.88-1.15 px (the tiny preset 0.47-0.58). There,
    # in focus (9 px, 0.7 px) RMS 0.034 mm, coverage 94.8 %; defocused 0.095 mm, 83.6 %; defocused with 13 px
    # 0.067 mm, 88.0 %; 17 px 0.060 mm; 13 px and 1.4 px 0.059 mm; 13 px and 2.0 px 0.054 mm, 89.2 %; 17 px and
    # 2.0 px 0.054 mm; 13 px and 2.6 px 0.062 mm; 15 px and 2.0 px 0.052 mm, 89.5 %. The in-focus images matched
    # so: 0.039 mm (hence the switch). Held out (seed 34): in focus 0.55-0.71 px, defocused 0.85-1.18 px
    blurred_above_px: float = 0.8
    blurred_lsm_window: int = 15
    blurred_antialias_px: float = 2.0
    # least-squares matching leaves out pixels at or above this share of the images' full scale (saturated, or
    # resampled mostly from saturated pixels) in either window: a clipped highlight moves with the view, not with
    # the skin. Tuned on seed 35, arm A, paper scale, true calibration: oily skin / middle camera 1 EV over, RMS
    # 0.0540 / 0.0471 mm with nothing left out; 0.98: 0.0526 / 0.0439 mm (the clean capture unchanged, 0.034 mm);
    # 0.995: 0.0521 / 0.0441; 0.9: 0.0546 / 0.0458; 0.8: 0.0563 / 0.0495 (bright unclipped pattern lost)
    saturated_share: float = 0.98
    # grey level of that (set from the images' full scale by tracking.track_images; inf: nothing left out)
    saturated_level: float = np.inf
    # stage 3, region growing from the matched points (see match_points)
    # rounds (at most; growing stops when a round matches nothing new): each one reaches a little further into
    # steep skin. Paper scale, arm D, coverage / time of the arm: 4 rounds 84.0% / 30.6 s; 12: 85.9% / 35.2 s;
    # 40: 86.2% / 39.2 s. But the steep skin the later rounds reach pulls the registration off: tiny preset,
    # torso RMS 1.43 mm with 12 rounds (0.67 mm with 4); paper scale, with 12 rounds and growing's least-squares
    # window at 11 px, the arms' mean position error 0.0196 mm (0.0106 mm before). Since the template is blurred to
    # the squeezed view's detail (lsm_antialias_px, 0.9 px here) the later rounds reach much further into the
    # steep skin: arms C / D 87.4 / 87.0% with 4 rounds, 89.1 / 88.4% with 8, 89.4 / 88.9% with 12, 89.5 / 89.0%
    # with 16
    # (one arm in a fresh process, arm D 15.2 s with 4, 15.4 s with 12, 16.2 s with 16). With growing's 16-px
    # neighbourhood (grow_radius_px) eight rounds reach as far: arm D 89.85% against 89.89% with 12
    grow_passes: int = 8
    # matched points this close (px), at least this many, predict an unmatched point's disparity plane. A wider
    # neighbourhood lets growing cross the gaps between the steep skin's features: paper scale, arms C / D 89.2 /
    # 88.5% with 12 px and 4; 16 px: 90.2 / 89.8%; 16 px and 3: 90.3 / 89.9%; 20 px: D 89.9%, 24 px: 90.0% (1 s
    # slower per arm)
    grow_radius_px: float = 16.0
    grow_min_neighbours: int = 3
    grow_search_px: int = 3  # columns searched either side of the predicted disparity
    grow_scale_range: tuple = (0.3, 3.0)  # predicted stretches outside this are not tried
    # least-squares precision a grown match needs (x shift, 1-sigma). Paper scale, arm C, 40 rounds, flanks kept:
    # 0.1 px: coverage 85.1%, RMS 0.038 mm; 0.25 px: 86.6%, 0.041 mm, but on the tiny preset (2 mm pixels) a wrong match 5.8 mm off
    # the skin passes every later test
    grow_max_lsm_sigma_px: float = 0.1
    # window of the grown matches (px): the stretch and shear are predicted, so a larger window no longer loses
    # correlation to foreshortening, and holds enough of the squeezed pattern for least-squares matching
    # (least-squares matching started at the true match, paper scale, skin seen 60-70 deg off its normal:
    # 78% converged within 0.1 px with 7 px, 94% with 11 px; 70-78 deg: 40% and 72%)
    grow_window: int = 11
    chunk: int = 4000  # points per block of least-squares matching (the blocks are shared out to the threads)
    # points per block of the correlation search (recon_engine.kernels, one point at a time): the blocks are
    # shared out to the threads
    search_chunk: int = 2000
    # blocks run in this many threads (numba, numpy and OpenCV release the GIL); 0: one per core
    threads: int = 0


def focus_adapted(cfg: MatchingConfig, blur_px: float) -> MatchingConfig:
    """The matching settings for an image pair whose blurrier image reads ``blur_px`` (``features.blur_sigma``):
    ``cfg`` itself in focus (or unknown, NaN), its ``blurred_*`` least-squares settings beyond
    ``cfg.blurred_above_px``."""
    if not blur_px > cfg.blurred_above_px:
        return cfg
    return replace(cfg, lsm_window=cfg.blurred_lsm_window, lsm_antialias_px=cfg.blurred_antialias_px)


def _kernel_array(a, dtype, shape=None) -> np.ndarray:
    """``a`` as the compiled kernels take it: C-contiguous, writable (numba compiles read-only arrays, such as
    numpy's broadcast views, separately), of ``dtype``, broadcast to ``shape``; a copy only where needed."""
    a = np.asarray(a, dtype=dtype)
    if shape is not None:
        a = a.reshape(shape) if a.size == np.prod(shape) else np.broadcast_to(a, shape)
    a = np.ascontiguousarray(a)
    return a if a.flags.writeable else a.copy()


def ncc_search(left: np.ndarray, right: np.ndarray, xy: np.ndarray, x_pred: np.ndarray, radius: int,
               band: int, window: int, exclude: int = 2, scale=1.0, shear=0.0) -> dict:
    """Best NCC match of each left point in the right image around ``x_pred``.

    Parameters
    ----------
    left, right : (H, W) arrays
        Rectified images.
    xy : (N, 2) array
        Left points (px).
    x_pred : (N,) array
        Centre of each search along the row (px, right image).
    radius : int
        Columns searched either side of ``x_pred``.
    band : int
        Rows searched either side of the point's own row.
    window : int
        Side of the correlation window (odd, px).
    exclude : int
        Columns either side of the peak left out of the second peak.
    scale : float or (N,) array
        Column spacing of the right window (px per left px): a surface patch
        foreshortened differently in the two views appears stretched along
        the row by this factor; the search steps scale with it.
    shear : float or (N,) array
        Column shift of the right window per row below the point (px per
        row): a surface whose depth changes along the epipolar lines' normal
        appears sheared by this much.

    Returns ``{"xy": (N, 2) right points, "ncc": (N,), "second": (N,),
    "at_edge": (N,) bool}``; ``at_edge`` means the peak lies on the border of
    the searched range, so the true peak may lie outside it.
    """
    n = len(xy)
    out, best, second, at_edge = ncc_points(_kernel_array(left, np.float32), _kernel_array(right, np.float32),
                                            _kernel_array(xy, float, (n, 2)),
                                            _kernel_array(np.round(x_pred), float, (n,)),
                                            _kernel_array(scale, float, (n,)), _kernel_array(shear, float, (n,)),
                                            int(radius), int(band), int(window), int(exclude))
    return {"xy": out, "ncc": best, "second": second, "at_edge": at_edge}


def _chunked(fn, n, chunk, threads=1, order=None, **arrays):
    """``fn`` over blocks of at most ``chunk`` of the length-``n`` arrays, in ``threads`` threads, concatenated.

    With ``order`` (a permutation of the n points) the blocks take the points in that order; the results come
    back in the points' own order.
    """
    if n < 256:
        threads = 1  # starting threads costs more than a few hundred points' work (region growing's later rounds)
    if threads > 1:
        chunk = max(1, min(chunk, -(-n // threads)))  # every thread gets a block
    if order is not None:
        arrays = {k: v[order] if isinstance(v, np.ndarray) and len(v) == n else v for k, v in arrays.items()}

    def run(s):
        return fn(**{k: v[s:s + chunk] if isinstance(v, np.ndarray) and len(v) == n else v
                     for k, v in arrays.items()})

    starts = range(0, n, chunk)
    if threads > 1 and len(starts) > 1:
        with ThreadPoolExecutor(threads) as pool:
            parts = list(pool.map(run, starts))
    else:
        parts = [run(s) for s in starts]
    if not parts:
        return {"xy": np.zeros((0, 2)), "ncc": np.zeros(0), "second": np.zeros(0), "at_edge": np.zeros(0, bool)}
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    if order is not None:
        for v in out.values():
            v[order] = v.copy()
    return out


def along_rows(xy: np.ndarray) -> np.ndarray:
    """The points ``xy`` (N, 2) row by row (a stable sort of their whole rows): the compiled kernels then read
    neighbouring points' windows from the cache (Harris features come strongest first, scattered over the image:
    the correlation search 1.4x faster row by row, benchmarks/bench_matching_kernels.py)."""
    rows = np.clip(np.floor(np.nan_to_num(xy[:, 1])), -32768, 32767).astype(np.int16)  # int16: numpy's radix sort
    return np.argsort(rows, kind="stable")


def _search(left, right, xy, x_pred, radius, band, window, cfg, scale=1.0, shear=0.0):
    n = len(xy)
    scale = np.broadcast_to(np.asarray(scale, dtype=float), (n,)).copy()
    shear = np.broadcast_to(np.asarray(shear, dtype=float), (n,)).copy()
    return _chunked(lambda **a: ncc_search(left, right, a["xy"], a["x_pred"], radius, band, window, scale=a["scale"],
                                           shear=a["shear"]),
                    n, cfg.search_chunk, cores(cfg.threads), along_rows(xy),
                    xy=xy, x_pred=x_pred, scale=scale, shear=shear)


def seed_disparities(left, right, xy, d_mid, radius, cfg):
    """Stage 1: disparities of the seed points ``xy`` from the whole range ``d_mid`` ± ``radius`` (px).

    With ``cfg.sparse_level`` > 0 the whole range is searched in the
    image pyramid's level of that many halvings (a window of the same
    footprint on the skin), and each peak is then found again at full
    resolution within a few columns of it: the long search costs a quarter
    (or less) of the full-resolution one per level. The uniqueness test is
    the long search's; the correlation and the subpixel peak are the full
    resolution's. With ``cfg.sparse_level_fallback`` the seeds the coarse
    level rejects search the whole range at full resolution. Short ranges
    (``radius`` below ``cfg.sparse_level_min_radius``) are searched at full
    resolution only: they are cheap there, and images whose pattern is
    barely resolved lose it at the coarser level. Returns (seed points,
    their disparities) that pass.
    """
    levels = cfg.sparse_level if radius >= cfg.sparse_level_min_radius else 0
    f = 2 ** levels
    if levels == 0:
        r = _search(left, right, xy, xy[:, 0] - d_mid, radius, 0, cfg.sparse_window, cfg)
        ok = (r["ncc"] >= cfg.sparse_min_ncc) & (r["second"] < cfg.uniqueness * r["ncc"]) & ~r["at_edge"]
        return xy[ok], (xy[:, 0] - r["xy"][:, 0])[ok]
    small_left, small_right = left, right
    for _ in range(levels):
        # Gaussian 5-tap smoothing before each halving; level pixel i lies on pixel 2i of the level below
        small_left, small_right = cv2.pyrDown(small_left), cv2.pyrDown(small_right)
    coarse = _search(small_left, small_right, xy / f, (xy[:, 0] - d_mid) / f, -(-radius // f) + 1, 0,
                     max(3, cfg.sparse_window // f) | 1, cfg)
    ok = (coarse["ncc"] >= cfg.sparse_min_ncc) & (coarse["second"] < cfg.uniqueness * coarse["ncc"]) & ~coarse["at_edge"]
    # the coarse peak is within half a level pixel (plus its subpixel error): search f + 1 columns either side
    fine = _search(left, right, xy[ok], coarse["xy"][ok, 0] * f, f + 1, 0, cfg.sparse_window, cfg)
    found = (fine["ncc"] >= cfg.sparse_min_ncc) & ~fine["at_edge"]
    seeds, d = [xy[ok][found]], [(xy[ok, 0] - fine["xy"][:, 0])[found]]
    if cfg.sparse_level_fallback:
        # where the pyramid loses the pattern (steep skin squeezes it in one view) the full resolution may not
        rest = xy[~ok]
        seeds_rest, d_rest = seed_disparities(left, right, rest, d_mid, radius, replace(cfg, sparse_level=0))
        seeds.append(seeds_rest)
        d.append(d_rest)
    return np.concatenate(seeds), np.concatenate(d)


def _window_shape(grad: np.ndarray) -> tuple:
    """Stretch and shear of the right window from the disparity plane's gradient (N, 2) (px/px).

    ``x_right = x_left - d(x, y)``: the window's columns stretch by
    ``1 - dd/dx`` and shift by ``-dd/dy`` per row.
    """
    return 1.0 - grad[:, 0], -grad[:, 1]


def _plane_prediction(anchors, d_anchor, nb, xy):
    """Disparity at ``xy`` from a plane through each point's neighbouring anchors (median where degenerate).

    Returns (disparity (N,), gradient (N, 2) px/px: zero where the median stands in).
    """
    med = np.median(d_anchor[nb], axis=1)
    plane, grad, ok = _plane_fit(anchors, d_anchor, nb, xy, max_cond=1e8)
    # a plane that strays far from its anchors (a wrong anchor) falls back to the median
    spread = np.ptp(d_anchor[nb], axis=1)
    ok &= np.abs(plane - med) <= spread + 1.0
    return np.where(ok, plane, med), np.where(ok[:, None], grad, 0.0)


def _plane_fit(anchors, d_anchor, nb, xy, max_cond: float = 1e6):
    """Disparity plane through each point's neighbours ``nb``: (value at ``xy``, (N, 2) gradient, fit ok)."""
    A = np.concatenate([np.ones(nb.shape + (1,)), anchors[nb] - xy[:, None, :]], axis=2)  # (n, k, 3)
    N = np.einsum("nki,nkj->nij", A, A)
    b = np.einsum("nki,nk->ni", A, d_anchor[nb])
    lam = np.linalg.eigvalsh(N)  # N is symmetric: its condition number from the eigenvalues (cheaper than an SVD)
    ok = lam[:, 0] * max_cond > lam[:, -1]
    sol = np.zeros((len(xy), 3))
    if ok.any():
        sol[ok] = np.linalg.solve(N[ok], b[ok][..., None])[..., 0]
    return sol[:, 0], sol[:, 1:], ok


def _verify(left, right, xy, r, scale, shear, cfg, max_sigma_px=None, window=None):
    """Checks of NCC matches ``r`` of left points ``xy`` and their least-squares refinement.

    Returns ``(reason, xy_right, ncc)``: reason "" for an accepted match,
    right points NaN for the others.
    """
    n = len(xy)
    window = window or cfg.window
    scale = np.broadcast_to(np.asarray(scale, dtype=float), (n,))
    shear = np.broadcast_to(np.asarray(shear, dtype=float), (n,))
    reason = np.full(n, "", dtype=object)
    out_xy = np.full((n, 2), np.nan)
    checks = [
        (r["at_edge"], "peak at the edge of the search range"),
        (r["ncc"] < cfg.min_ncc, "correlation below the minimum"),
        (r["second"] >= cfg.uniqueness * r["ncc"], "not unique (second peak too close)"),
    ]
    for bad, why in checks:
        reason[(reason == "") & bad] = why
    # left-right check of the rest: the right point matched back into the left image (inverse stretch and shear)
    idx = np.nonzero(reason == "")[0]
    back = _search(right, left, r["xy"][idx], xy[idx, 0], 2, 1, window, cfg, scale=1.0 / scale[idx],
                   shear=-shear[idx] / scale[idx])
    lr = np.hypot(back["xy"][:, 0] - xy[idx, 0], back["xy"][:, 1] - xy[idx, 1])
    reason[idx[lr > cfg.lr_tolerance_px]] = "left-right check failed"
    valid = reason == ""
    out_xy[valid] = r["xy"][valid]
    out_ncc = np.asarray(r["ncc"], dtype=float).copy()
    if cfg.refine and valid.any():
        idx = np.nonzero(valid)[0]
        lsm_window = cfg.lsm_window or window
        lsm = _chunked(lambda **a: least_squares_refine(left, right, a["xy_left"], a["xy_right"], window=lsm_window,
                                                        initial_scale=a["scale"], initial_shear=a["shear"],
                                                        antialias_px=cfg.lsm_antialias_px,
                                                        clip=cfg.saturated_level),
                       len(idx), cfg.chunk * 2, cores(cfg.threads), along_rows(xy[idx]), xy_left=xy[idx],
                       xy_right=r["xy"][idx],
                       scale=np.ascontiguousarray(scale[idx]), shear=np.ascontiguousarray(shear[idx]))
        limit = cfg.max_lsm_sigma_px if max_sigma_px is None else max_sigma_px
        good = lsm["converged"] & (lsm["rho"] >= cfg.min_lsm_rho) & (lsm["sigma"] <= limit)
        reason[idx[~good]] = "least-squares matching failed"
        out_xy[idx[good]] = lsm["xy"][good]
        out_xy[idx[~good]] = np.nan
        out_ncc[idx] = lsm["rho"]
    return reason, out_xy, out_ncc


def match_points(left: np.ndarray, right: np.ndarray, xy: np.ndarray, disparity_range: tuple[float, float],
                 cfg: MatchingConfig | None = None) -> dict:
    """Match left points ``xy`` (N, 2) into the right image of a rectified pair.

    ``disparity_range`` is (min, max) of ``x_left - x_right`` (px) for the
    subject's depth bounds. With ``cfg.refine`` the correlation peaks are
    refined by least-squares matching and ``ncc`` is its final correlation.
    Returns ``{"xy": (N, 2) right points, "ncc": (N,),
    "valid": (N,) bool, "reason": (N,) str}``; ``reason`` says why a point
    is not matched ("" when it is).
    """
    cfg = cfg or MatchingConfig()
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    n = len(xy)
    reason = np.full(n, "", dtype=object)
    out_xy = np.full((n, 2), np.nan)
    out_ncc = np.full(n, -1.0)
    if n == 0:
        return {"xy": out_xy, "ncc": out_ncc, "valid": np.zeros(0, bool), "reason": reason}
    dmin, dmax = sorted(disparity_range)
    # stage 1: one point per anchor square over the whole range, big window, on its row
    cell = np.floor(xy / cfg.anchor_spacing).astype(np.int64)
    key = cell[:, 1] * (int(cell[:, 0].max()) + 2) + cell[:, 0]
    _, sparse = np.unique(key, return_index=True)
    radius = int(np.ceil((dmax - dmin) / 2)) + 1
    anchors, d_anchor = seed_disparities(left, right, xy[sparse], 0.5 * (dmin + dmax), radius, cfg)
    if len(anchors) >= 3:
        # drop anchors that disagree with their neighbours (a wrong peak of the repeating pattern)
        k = min(cfg.neighbours + 1, len(anchors))
        _, nb = cKDTree(anchors).query(anchors, k=k)
        med = np.median(d_anchor[nb[:, 1:]], axis=1)
        keep = np.abs(d_anchor - med) <= cfg.neighbour_tolerance_px
        anchors, d_anchor = anchors[keep], d_anchor[keep]
    if len(anchors) < 3:
        reason[:] = "no reliable disparity in the neighbourhood"
        return {"xy": out_xy, "ncc": out_ncc, "valid": np.zeros(n, bool), "reason": reason}
    # stage 2: every point, short range around the disparity its anchors'
    # local plane predicts (the disparity changes fast where the skin turns away)
    k = min(cfg.neighbours, len(anchors))
    dist, nb = cKDTree(anchors).query(xy, k=k)
    nb = nb.reshape(n, -1)
    d_pred, grad = _plane_prediction(anchors, d_anchor, nb, xy)
    tries = [(np.full(n, sc), np.zeros(n)) for sc in cfg.scales]
    if cfg.predicted_shape:
        # the anchors' plane predicts the right window's stretch (1 - dd/dx) and shear (-dd/dy) too
        lo, hi = cfg.grow_scale_range
        scale, shear = _window_shape(grad)
        tries.insert(0, (np.clip(scale, lo, hi), np.clip(shear, -1.0, 1.0)))
    if not tries:
        tries = [(np.ones(n), np.zeros(n))]
    best = None
    todo = np.arange(n)
    for sc, sh in tries:
        # other stretches only for the points the first window does not match well
        r = _search(left, right, xy[todo], xy[todo, 0] - d_pred[todo], cfg.dense_radius, cfg.band, cfg.window,
                    cfg, scale=sc[todo], shear=sh[todo])
        r["scale"], r["shear"] = sc[todo], sh[todo]
        if best is None:
            best = r
        else:
            better = r["ncc"] > best["ncc"][todo]
            for key in best:
                best[key][todo[better]] = r[key][better]
        weak = (best["ncc"] < cfg.retry_below_ncc) | best["at_edge"] | (best["second"] >= cfg.uniqueness * best["ncc"])
        todo = np.nonzero(weak)[0]
        if len(todo) == 0:
            break
    r2 = best
    # points far from every anchor have no prediction to trust: not verified (nor refined) at all
    far = np.asarray(dist).reshape(n, -1)[:, -1] > 6 * cfg.anchor_spacing
    near = np.nonzero(~far)[0]
    reason[far] = "no reliable disparity in the neighbourhood"
    out_ncc = np.asarray(r2["ncc"], dtype=float).copy()
    reason[near], out_xy[near], out_ncc[near] = _verify(left, right, xy[near], {k: v[near] for k, v in r2.items()},
                                                        r2["scale"][near], r2["shear"][near], cfg)
    # stage 3: region growing. Where the skin turns away from the cameras the disparity changes faster than
    # the anchors' planes follow, and the two views foreshorten it differently; the points matched so far
    # predict both (disparity, stretch and shear of the right window) right next to each unmatched point
    reason, out_xy, out_ncc = _grow(left, right, xy, reason, out_xy, out_ncc, cfg)
    valid = reason == ""
    return {"xy": out_xy, "ncc": out_ncc, "valid": valid, "reason": reason}


def grow_matches(left: np.ndarray, right: np.ndarray, xy: np.ndarray, xy_right: np.ndarray,
                 cfg: MatchingConfig | None = None) -> dict:
    """Region growing alone: left points ``xy`` (N, 2) whose right points ``xy_right`` (N, 2) are known (NaN
    where not) predict the disparity, stretch and shear of their unmatched neighbours (stage 3 of
    ``match_points``).

    The known matches are kept as they are. Returns the same as ``match_points``; ``reason`` is "not reached"
    for points growing never tried, ``ncc`` NaN for the known matches (they were not correlated here).
    """
    cfg = cfg or MatchingConfig()
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    out_xy = np.array(xy_right, dtype=float).reshape(-1, 2)
    known = np.isfinite(out_xy).all(axis=1)
    reason = np.where(known, "", "not reached").astype(object)
    out_ncc = np.where(known, np.nan, -1.0)
    reason, out_xy, out_ncc = _grow(left, right, xy, reason, out_xy, out_ncc, cfg)
    valid = reason == ""
    return {"xy": out_xy, "ncc": out_ncc, "valid": valid, "reason": reason}


def _grow(left, right, xy, reason, out_xy, out_ncc, cfg):
    """Rounds of region growing from the points with ``reason`` "" (see ``match_points``); new arrays returned."""
    reason, out_xy, out_ncc = reason.copy(), out_xy.copy(), out_ncc.copy()
    valid = reason == ""
    if valid.sum() < 3 or valid.all():
        return reason, out_xy, out_ncc
    # the matched points in two k-d trees: those at the start, built once, and those matched since, a small tree
    # rebuilt each round (a round's new matches are few: rebuilding one tree of all matched points each round
    # cost more than the later rounds' matching)
    start = np.nonzero(valid)[0]
    start_tree = cKDTree(xy[start])
    since = np.zeros(0, np.int64)
    fresh = None  # points matched in the last round: only their neighbourhoods have anything new to offer
    for _ in range(cfg.grow_passes):
        todo = np.nonzero(~valid)[0]
        if fresh is not None:
            # the unmatched points within reach of a new match (a hair further than the neighbours' bound)
            d, _ = cKDTree(xy[fresh]).query(xy[todo], k=1, distance_upper_bound=cfg.grow_radius_px * (1 + 1e-9))
            todo = todo[np.isfinite(d)]
        if len(todo) == 0:
            break
        nb = matched_neighbours(start_tree, start, since, xy, todo, cfg)
        enough = np.sum(nb >= 0, axis=1) >= cfg.grow_min_neighbours
        if fresh is not None:
            # a point whose nearest matched neighbours are the last round's set again would be predicted, searched
            # and rejected as then: only those a new match joined are tried again (exactly the same result)
            enough &= np.isin(nb, fresh).any(axis=1)
        todo, nb = todo[enough], nb[enough]
        if len(todo) == 0:
            break
        # missing neighbours (beyond the radius) repeat the nearest one: it adds nothing to the plane
        nb = np.where(nb < 0, nb[:, :1], nb)
        d_pred, grad, fit = _plane_fit(xy, xy[:, 0] - out_xy[:, 0], nb, xy[todo])
        scale, shear = _window_shape(grad)
        ok = fit & (scale >= cfg.grow_scale_range[0]) & (scale <= cfg.grow_scale_range[1]) & (np.abs(shear) <= 1.0)
        todo, d_pred, scale, shear = todo[ok], d_pred[ok], scale[ok], shear[ok]
        if len(todo) == 0:
            break
        r3 = _search(left, right, xy[todo], xy[todo, 0] - d_pred, cfg.grow_search_px, cfg.band, cfg.grow_window, cfg,
                     scale=scale, shear=shear)
        why, xy3, ncc3 = _verify(left, right, xy[todo], r3, scale, shear, cfg, cfg.grow_max_lsm_sigma_px,
                                 cfg.grow_window)
        won = why == ""
        reason[todo] = np.where(won, "", why)  # the last attempt's verdict
        if not won.any():
            break
        fresh = todo[won]
        since = np.concatenate([since, fresh])
        valid[fresh] = True
        out_xy[fresh] = xy3[won]
        out_ncc[fresh] = ncc3[won]
        if valid.all():
            break
    return reason, out_xy, out_ncc


def matched_neighbours(start_tree, start, since, xy, todo, cfg) -> np.ndarray:
    """The ``cfg.neighbours`` nearest matched points within ``cfg.grow_radius_px`` of each of the points ``todo``:
    (len(todo), k) indices into ``xy``, nearest first, -1 where there are fewer.

    The matched points are ``start`` (indices into ``xy``; ``start_tree`` their k-d tree) and ``since``.
    """
    k = min(cfg.neighbours, len(start) + len(since))
    q = xy[todo]
    dist, idx = [], []
    for ids, tree in ((start, start_tree), (since, cKDTree(xy[since]) if len(since) else None)):
        if tree is None or len(ids) == 0:
            continue
        kk = min(k, len(ids))
        d, i = tree.query(q, k=kk, distance_upper_bound=cfg.grow_radius_px)
        d, i = d.reshape(len(q), kk), i.reshape(len(q), kk)
        dist.append(d)
        idx.append(np.where(np.isfinite(d), ids[np.minimum(i, len(ids) - 1)], -1))
    dist, idx = np.concatenate(dist, axis=1), np.concatenate(idx, axis=1)
    if len(dist) and dist.shape[1] > k:
        order = np.argsort(dist, axis=1, kind="stable")[:, :k]  # missing ones (inf) last
        idx = np.take_along_axis(idx, order, axis=1)
    return idx


def reason_counts(reason: np.ndarray) -> dict:
    """How many times each reason (str) occurs in ``reason``, for a report."""
    why, count = np.unique(np.asarray(reason).astype(str), return_counts=True)
    return {str(w): int(c) for w, c in zip(why, count)}


def _antialias_sigma(scale, antialias_px):
    """Blur (template px, Gaussian sigma along the rows) that brings a template to the detail of a right window
    stretched by ``scale`` (< 1: squeezed); 0 where it is not squeezed."""
    return antialias_px * np.sqrt(np.maximum(1.0 / np.maximum(scale, 0.1) ** 2 - 1.0, 0.0))


def least_squares_refine(left: np.ndarray, right: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray,
                         window: int = 11, iterations: int = 8, shift_y: bool = True, initial_scale=1.0,
                         initial_shear=0.0, antialias_px: float = 0.0, clip: float = np.inf,
                         _again: bool = True) -> dict:
    """Adaptive least-squares matching (Gruen 1985) of windows already matched to about a pixel.

    The right window is an affine image of the left one along the row
    (``x' = x + a0 + (s - 1)·dx + t·dy``, ``y' = y + b0``) with a
    radiometric gain and offset; the stretch ``s`` and shear ``t`` absorb the
    different foreshortening of a surface patch in the two images, which
    biases a plain correlation peak. ``initial_scale`` and ``initial_shear``
    start ``s`` and ``t``.

    Solved in the inverse-compositional form (Baker & Matthews 2004): the
    Jacobian is the left window's (the template's) gradient, so the normal
    equations are formed and inverted once per point, and each iteration
    only samples the right window; the warp is updated by composing it with
    the inverse of the increment. The gain and offset are projected out of
    the geometric parameters (the Schur complement of the full normal
    equations). The x shift's precision is the forward adjustment's, from
    the right window's gradients at the solution. Each point is solved in a
    compiled loop (``kernels.lsm_points``) with exact bilinear samples.

    ``antialias_px`` (px, 0: off) is the blur of an image in its own pixels
    (pixel footprint, optics and resampling, as a Gaussian's sigma). Where
    the right window is squeezed (``initial_scale`` s < 1), each of its
    pixels averages 1/s template pixels of skin: the template is blurred
    along its rows by ``antialias_px · sqrt(1/s² − 1)`` template px so that
    both windows hold the same detail; the pattern's finer detail, which the
    squeezed view lost, would otherwise count as misfit.

    Pixels at or above the grey level ``clip`` (saturated), or next to one, in
    the template or in the right window where it starts, take no part; a
    point with more than half its window so is not converged.

    Returns ``{"xy": (N, 2) refined right points (px), "sigma": (N,) px
    standard deviation of the x shift, "rho": (N,) final correlation,
    "converged": (N,) bool}``.
    """
    n = len(xy_left)
    s_start, t_start = _kernel_array(initial_scale, float, (n,)), _kernel_array(initial_shear, float, (n,))
    xy_left = _kernel_array(xy_left, float, (n, 2))
    left, right = _kernel_array(left, np.float32), _kernel_array(right, np.float32)
    blur = _antialias_sigma(s_start, antialias_px)  # the kernel caps it at 3 px
    xy, sigma, rho, converged, s, t = lsm_points(left, right, xy_left, _kernel_array(xy_right, float, (n, 2)),
                                                 int(window), int(iterations), bool(shift_y), s_start, t_start, blur,
                                                 float(clip))
    out = {"xy": xy, "sigma": sigma, "rho": rho, "converged": converged}
    if antialias_px > 0 and _again:
        # the template's blur followed the starting stretch; where the solved one asks for a clearly different blur
        # (a guessed start, or a plane's noise on unsqueezed skin) the point is solved again from there with it
        blur_solved = _antialias_sigma(s, antialias_px)
        redo = np.nonzero(converged & (np.abs(blur_solved - blur) > 0.1))[0]
        if len(redo):
            again = lsm_points(left, right, xy_left[redo], xy[redo], int(window), int(iterations), bool(shift_y),
                               s[redo], t[redo], blur_solved[redo], float(clip))
            for key, value in zip(("xy", "sigma", "rho", "converged"), again[:4]):
                out[key][redo] = value
    return out
