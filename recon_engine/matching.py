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

All coordinates are rectified pixels (x = column, y = row).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .imaging import sample_bilinear
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
    chunk: int = 4000  # points per vectorized block of least-squares matching (memory)
    # right-image samples per block of the correlation search: its window loop passes over the block's strips
    # once per window pixel, so blocks that stay in the core's cache run faster (synthetic pair, 7-px window,
    # 13 x 5 positions: 11.5-14 us per point in blocks of 2000 points, 25-30 us in blocks of 9877)
    search_block: int = 400_000
    # blocks run in this many threads (numpy and OpenCV release the GIL in the array work); 0: one per core
    threads: int = 0


def sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Exact bilinear samples (float32) of ``image`` at float positions; 0 outside.

    OpenCV's remap would step positions by 1/32 px, too coarse for least-squares matching.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    h, w = image.shape
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    # float32 weights: 1e-7 relative, far below the 1e-3 px the refinement resolves
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
    i = np.clip(y0, 0, h - 2) * w + np.clip(x0, 0, w - 2)
    flat = np.asarray(image, dtype=np.float32).ravel()
    v = (flat[i] * ((1 - fx) * (1 - fy)) + flat[i + 1] * (fx * (1 - fy)) + flat[i + w] * ((1 - fx) * fy)
         + flat[i + w + 1] * (fx * fy))
    v[~inside] = 0
    return v


def sample_grid(image: np.ndarray, xy: np.ndarray, off_x: np.ndarray, off_y: np.ndarray) -> np.ndarray:
    """Exact bilinear samples (N, len(off_y), len(off_x)) float32 of ``image`` on grids of whole-pixel offsets
    ``off_x``, ``off_y`` (consecutive integers) around points ``xy`` (N, 2); 0 outside, as ``sample``.

    Every sample of a grid shares its point's fraction: one gather of each
    point's patch of whole pixels, then four shifted slices weighted, about
    three times faster than ``sample``'s four gathers per sample.
    """
    xy = np.asarray(xy, dtype=float)
    h, w = image.shape
    R, C = len(off_y), len(off_x)
    x0 = np.floor(xy[:, 0]).astype(np.int64) + int(off_x[0])
    y0 = np.floor(xy[:, 1]).astype(np.int64) + int(off_y[0])
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + C < w) & (y0 + R < h)
    out = np.empty((len(xy), R, C), np.float32)
    if not inside.all():
        rest = ~inside
        out[rest] = sample(image, xy[rest, 0, None, None] + off_x[None, None, :],
                           xy[rest, 1, None, None] + off_y[None, :, None])
    idx = np.nonzero(inside)[0]
    if len(idx):
        img = np.ascontiguousarray(image, dtype=np.float32)
        patches = np.lib.stride_tricks.sliding_window_view(img, (R + 1, C + 1))[y0[idx], x0[idx]]
        fx = (xy[idx, 0] - np.floor(xy[idx, 0])).astype(np.float32)[:, None, None]
        fy = (xy[idx, 1] - np.floor(xy[idx, 1])).astype(np.float32)[:, None, None]
        top = patches[:, :-1, :-1] * (1 - fx) + patches[:, :-1, 1:] * fx
        bottom = patches[:, 1:, :-1] * (1 - fx) + patches[:, 1:, 1:] * fx
        out[idx] = top * (1 - fy) + bottom * fy
    return out


def _box(a: np.ndarray, win: int) -> np.ndarray:
    """Sums over ``win``×``win`` windows of the last two axes of (N, R, C) strips (valid part).

    The strips are stacked into one tall image for OpenCV's integral image; the
    windows read never straddle two strips. The running sums (float64) are
    exact when every value is a multiple of 2^-16 below 2^17 in a block of
    fewer than 2^19 values (see ``ncc_search``): a strip's sums then do not
    depend on the strips stacked above it.
    """
    n, R, C = a.shape
    integ = cv2.integral(np.ascontiguousarray(a, dtype=np.float32).reshape(n * R, C), sdepth=cv2.CV_64F)
    top = (np.arange(n)[:, None] * R + np.arange(R - win + 1)[None, :])  # (n, B)
    bottom = top + win
    It, Ib = integ[top], integ[bottom]  # (n, B, C + 1)
    return (Ib[..., win:] - Ib[..., :-win] - It[..., win:] + It[..., :-win]).astype(np.float32)


def _parabola(m, l, r):
    den = l - 2 * m + r
    off = np.where(den < 0, 0.5 * (l - r) / np.where(den < 0, den, -1), 0.0)
    return np.clip(off, -0.5, 0.5)


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
    h = window // 2
    n = len(xy)
    off = np.arange(-h, h + 1, dtype=float)
    lx = xy[:, 0, None, None] + off[None, None, :]
    ly = xy[:, 1, None, None] + off[None, :, None]
    # OpenCV's remap (1/32-px interpolation steps) is precise enough for a
    # correlation peak that least-squares matching refines afterwards
    L = sample_bilinear(left, np.broadcast_to(lx, (n, window, window)), np.broadcast_to(ly, (n, window, window)))
    L = L - L.mean(axis=(1, 2), keepdims=True)
    Lnorm = np.sqrt(np.sum(L * L, axis=(1, 2)))
    x0 = np.round(x_pred)
    sc = np.broadcast_to(np.asarray(scale, dtype=float), (n,))
    sh = np.broadcast_to(np.asarray(shear, dtype=float), (n,))
    cols = np.arange(-radius - h, radius + h + 1, dtype=float)
    rows = np.arange(-band - h, band + h + 1, dtype=float)
    sx = x0[:, None, None] + sc[:, None, None] * cols[None, None, :] + sh[:, None, None] * rows[None, :, None]
    sy = xy[:, 1, None, None] + rows[None, :, None]
    S = sample_bilinear(right, np.broadcast_to(sx, (n, len(rows), len(cols))),
                        np.broadcast_to(sy, (n, len(rows), len(cols))))
    S = S - S.mean(axis=(1, 2), keepdims=True)
    # on a grid of 1/256 grey level (far below the sensor's noise) every window sum of the strips and of their
    # squares is exact in float64: a point's correlations come out the same to the last bit however the points
    # are split into blocks and threads (worker processes of one thread and a service of two agree exactly)
    S = np.round(S * 256.0) / 256.0
    B, D = 2 * band + 1, 2 * radius + 1
    num = np.zeros((n, B, D), np.float32)
    product = np.empty_like(num)  # one buffer for every step's product (the same sums, 17% faster)
    # loop over the window's offsets (not the points): each step is one array operation
    for i in range(window):
        for j in range(window):
            np.multiply(S[:, i:i + B, j:j + D], L[:, i, j, None, None], out=product)
            num += product
    s1 = _box(S, window)
    s2 = _box(S * S, window)
    var = np.maximum(s2 - s1 * s1 / window ** 2, 0)
    den = Lnorm[:, None, None] * np.sqrt(var)
    ncc = np.where(den > 1e-6, num / np.maximum(den, 1e-12), -1.0)
    flat = ncc.reshape(n, -1)
    k = np.argmax(flat, axis=1)
    kb, kd = np.divmod(k, D)
    best = flat[np.arange(n), k]
    # second peak: the best column at least ``exclude`` away from the first, any row
    colmax = ncc.max(axis=1)
    far = np.abs(np.arange(D)[None, :] - kd[:, None]) > exclude
    second = np.where(far, colmax, -1.0).max(axis=1)
    at_edge = (kd == 0) | (kd == D - 1)
    idx = np.arange(n)
    kd_in = np.clip(kd, 1, D - 2)
    dx = _parabola(best, ncc[idx, kb, kd_in - 1], ncc[idx, kb, kd_in + 1])
    dx = np.where(at_edge, 0.0, dx)
    if band > 0:
        kb_in = np.clip(kb, 1, B - 2)
        dy = _parabola(best, ncc[idx, kb_in - 1, kd], ncc[idx, kb_in + 1, kd])
        dy = np.where((kb == 0) | (kb == B - 1), 0.0, dy)
    else:
        dy = np.zeros(n)
    out = np.column_stack([x0 + sc * (kd + dx - radius) + sh * (kb + dy - band), xy[:, 1] - band + kb + dy])
    return {"xy": out, "ncc": best.astype(float), "second": second.astype(float), "at_edge": at_edge}


def _chunked(fn, n, chunk, threads=1, **arrays):
    """``fn`` over blocks of at most ``chunk`` of the length-``n`` arrays, in ``threads`` threads, concatenated."""
    if n < 256:
        threads = 1  # starting threads costs more than a few hundred points' work (region growing's later rounds)
    if threads > 1:
        chunk = max(1, min(chunk, -(-n // threads)))  # every thread gets a block

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
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _search(left, right, xy, x_pred, radius, band, window, cfg, scale=1.0, shear=0.0):
    n = len(xy)
    scale = np.broadcast_to(np.asarray(scale, dtype=float), (n,)).copy()
    shear = np.broadcast_to(np.asarray(shear, dtype=float), (n,)).copy()
    return _chunked(lambda **a: ncc_search(left, right, a["xy"], a["x_pred"], radius, band, window, scale=a["scale"],
                                           shear=a["shear"]),
                    n, max(16, cfg.search_block // ((2 * band + window) * (2 * radius + window))), cores(cfg.threads),
                    xy=xy, x_pred=x_pred, scale=scale, shear=shear)


def _seed_disparities(left, right, xy, d_mid, radius, cfg):
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
        seeds_rest, d_rest = _seed_disparities(left, right, rest, d_mid, radius, replace(cfg, sparse_level=0))
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


def _verify(left, right, xy, r, scale, shear, cfg, max_sigma_px=None, prepared=None, window=None):
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
        if prepared is None:
            prepared = least_squares_image(right)
        lsm_window = cfg.lsm_window or window
        lsm = _chunked(lambda **a: least_squares_refine(left, right, a["xy_left"], a["xy_right"], window=lsm_window,
                                                        initial_scale=a["scale"], initial_shear=a["shear"],
                                                        prepared=prepared, antialias_px=cfg.lsm_antialias_px),
                       len(idx), cfg.chunk * 2, cores(cfg.threads), xy_left=xy[idx], xy_right=r["xy"][idx],
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
    anchors, d_anchor = _seed_disparities(left, right, xy[sparse], 0.5 * (dmin + dmax), radius, cfg)
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
    prepared = least_squares_image(right) if cfg.refine else None
    reason[far] = "no reliable disparity in the neighbourhood"
    out_ncc = np.asarray(r2["ncc"], dtype=float).copy()
    reason[near], out_xy[near], out_ncc[near] = _verify(left, right, xy[near], {k: v[near] for k, v in r2.items()},
                                                        r2["scale"][near], r2["shear"][near], cfg,
                                                        prepared=prepared)
    # stage 3: region growing. Where the skin turns away from the cameras the disparity changes faster than
    # the anchors' planes follow, and the two views foreshorten it differently; the points matched so far
    # predict both (disparity, stretch and shear of the right window) right next to each unmatched point
    reason, out_xy, out_ncc = _grow(left, right, xy, reason, out_xy, out_ncc, cfg, prepared)
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
    prepared = least_squares_image(right) if cfg.refine else None
    reason, out_xy, out_ncc = _grow(left, right, xy, reason, out_xy, out_ncc, cfg, prepared)
    valid = reason == ""
    return {"xy": out_xy, "ncc": out_ncc, "valid": valid, "reason": reason}


def _grow(left, right, xy, reason, out_xy, out_ncc, cfg, prepared):
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
        nb = _matched_neighbours(start_tree, start, since, xy, todo, cfg)
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
        why, xy3, ncc3 = _verify(left, right, xy[todo], r3, scale, shear, cfg, cfg.grow_max_lsm_sigma_px, prepared,
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


def _matched_neighbours(start_tree, start, since, xy, todo, cfg) -> np.ndarray:
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


def least_squares_image(image: np.ndarray) -> tuple:
    """What least-squares matching samples of an image, laid out for OpenCV's remap.

    Returns ``(corners, gradients)``: (H, W, 4) float32 of each pixel's
    2×2 neighbourhood (value at x, x+1, and one row below), so that one
    nearest-pixel fetch gives all four corners of an exact bilinear sample;
    and (H, W, 2) float32 central-difference gradients d/dx, d/dy.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    h, w = img.shape
    padded = np.zeros((h + 1, w + 1), np.float32)  # zeros beyond the last row and column
    padded[:h, :w] = img
    # interleaving in OpenCV from views of one padded copy: numpy's stack along the last axis is slow
    corners = cv2.merge([padded[:h, :w], padded[:h, 1:], padded[1:, :w], padded[1:, 1:]])
    # central differences (as numpy's gradient inside the image); OpenCV's filter is several times faster
    gradients = cv2.merge([cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE),
                           cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)])
    return corners, gradients


def _sample_windows(corners: np.ndarray, pixel: np.ndarray, local_x: np.ndarray, local_y: np.ndarray) -> np.ndarray:
    """Exact bilinear values (float32) of ``least_squares_image`` output at ``pixel + local`` positions.

    ``pixel`` (N, 2) are whole pixels (x, y), ``local_x``, ``local_y`` (N, M)
    float32 offsets from them (a window's positions, a few px): split so
    that float32 keeps the fractions to 1e-6 px. The four corners come from
    one nearest-pixel remap (fast, in OpenCV) and are weighted here with the
    exact fractions: OpenCV's bilinear remap rounds positions to 1/32 px, too
    coarse for least-squares matching, which resolves about 1/1000 px.
    """
    h, w = corners.shape[:2]
    x0, y0 = np.floor(local_x), np.floor(local_y)
    fx, fy = local_x - x0, local_y - y0
    x0 += pixel[:, 0, None].astype(np.float32)
    y0 += pixel[:, 1, None].astype(np.float32)
    c = sample_bilinear(corners, x0, y0, interpolation=cv2.INTER_NEAREST)
    top = c[..., 0] + fx * (c[..., 1] - c[..., 0])
    bottom = c[..., 2] + fx * (c[..., 3] - c[..., 2])
    value = top + fy * (bottom - top)
    value[(x0 < 0) | (y0 < 0) | (x0 >= w - 1) | (y0 >= h - 1)] = 0
    return value


def _projected_normal_equations(sd: np.ndarray, centred: np.ndarray, ridge: float) -> tuple:
    """Steepest-descent images ``sd`` (N, K, M) with a radiometric offset and gain projected out, and their normal equations.

    The offset is the window's mean, the gain the mean-free window ``centred``
    (N, M) itself: removing both components (the Schur complement of the full
    normal equations) leaves the geometric parameters' system. ``ridge`` (a
    fraction of the trace) keeps nearly flat windows invertible. Returns the
    projected ``sd`` (a new array) and ``N`` (N, K, K) float64.
    """
    sd = sd - sd.mean(axis=2, keepdims=True)
    c2 = np.maximum(np.sum(centred * centred, axis=1), 1e-12)
    sd -= (np.einsum("nkm,nm->nk", sd, centred) / c2[:, None])[..., None] * centred[:, None, :]
    N = np.einsum("nkm,njm->nkj", sd, sd).astype(float)
    N += np.eye(sd.shape[1])[None] * ridge * np.trace(N, axis1=1, axis2=2)[:, None, None]
    return sd, N


def _antialias_sigma(scale, antialias_px):
    """Blur (template px, Gaussian sigma along the rows) that brings a template to the detail of a right window
    stretched by ``scale`` (< 1: squeezed); 0 where it is not squeezed."""
    return antialias_px * np.sqrt(np.maximum(1.0 / np.maximum(scale, 0.1) ** 2 - 1.0, 0.0))


def _template(left, xy_left, wide, scale, antialias_px):
    """Template windows (N, len(wide), len(wide)) of ``left`` at ``xy_left`` (whole-pixel offsets ``wide``, px;
    exact bilinear samples), blurred along the rows where the right window is squeezed (stretch ``scale`` < 1;
    see ``least_squares_refine``)."""
    sigma = np.minimum(_antialias_sigma(scale, antialias_px), 3.0)
    blur = sigma > 0.05
    if not blur.any():
        return sample_grid(left, xy_left, wide, wide)
    T = np.empty((len(xy_left), len(wide), len(wide)), np.float32)
    if not blur.all():
        T[~blur] = sample_grid(left, xy_left[~blur], wide, wide)
    # each point's kernel reaches 3 sigma: points grouped by its reach, so that a point's template does not depend
    # on the other points in its block (matches exact to the bit however the points are split)
    reach = np.ceil(3 * sigma).astype(int)
    C = len(wide)
    for r in np.unique(reach[blur]):
        idx = np.nonzero(blur & (reach == r))[0]
        taps = np.arange(-r, r + 1, dtype=float)
        g = np.exp(-0.5 * (taps[None, :] / sigma[idx, None]) ** 2)
        g = (g / g.sum(axis=1, keepdims=True)).astype(np.float32)
        # the rows sampled r px wider either side, then each point's kernel along them, one tap at a time
        W = sample_grid(left, xy_left[idx], np.arange(wide[0] - r, wide[-1] + r + 1, dtype=float), wide)
        acc = W[:, :, 0:C] * g[:, 0, None, None]
        for k in range(1, 2 * r + 1):
            acc += W[:, :, k:k + C] * g[:, k, None, None]
        T[idx] = acc
    return T


def least_squares_refine(left: np.ndarray, right: np.ndarray, xy_left: np.ndarray, xy_right: np.ndarray,
                         window: int = 11, iterations: int = 8, shift_y: bool = True, initial_scale=1.0,
                         initial_shear=0.0, prepared: tuple | None = None, antialias_px: float = 0.0,
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
    the right window's gradients at the solution. All points are solved at
    once, vectorized; 2.1x faster than the forward-additive form
    (a new Jacobian and normal equations at every iteration) that it replaced
    (40 000 synthetic windows of 9 px, docs/benchmarks.md).

    ``prepared`` is ``least_squares_image(right)``: pass it in when refining
    several batches on one image.

    ``antialias_px`` (px, 0: off) is the blur of an image in its own pixels
    (pixel footprint, optics and resampling, as a Gaussian's sigma). Where
    the right window is squeezed (``initial_scale`` s < 1), each of its
    pixels averages 1/s template pixels of skin: the template is blurred
    along its rows by ``antialias_px · sqrt(1/s² − 1)`` template px so that
    both windows hold the same detail; the pattern's finer detail, which the
    squeezed view lost, would otherwise count as misfit.

    Returns ``{"xy": (N, 2) refined right points (px), "sigma": (N,) px
    standard deviation of the x shift, "rho": (N,) final correlation,
    "converged": (N,) bool}``.
    """
    h = window // 2
    n = len(xy_left)
    m = window * window
    off = np.arange(-h, h + 1, dtype=np.float32)
    ex = np.tile(off, window)  # the window's pixel offsets (row by row)
    ey = np.repeat(off, window)
    # the template and its gradients: central differences of samples one pixel wider, which equal the bilinear
    # interpolation of the image's central differences at the same fractions
    wide = np.arange(-h - 1, h + 2, dtype=float)
    xy_left = np.asarray(xy_left, dtype=float)
    T = _template(left, xy_left, wide, np.broadcast_to(np.asarray(initial_scale, dtype=float), (n,)), antialias_px)
    L = np.ascontiguousarray(T[:, 1:-1, 1:-1]).reshape(n, m)
    Lx = (0.5 * (T[:, 1:-1, 2:] - T[:, 1:-1, :-2])).reshape(n, m)
    Ly = (0.5 * (T[:, 2:, 1:-1] - T[:, :-2, 1:-1])).reshape(n, m)
    # the steepest-descent images of the parameters (x shift, stretch, shear, y shift) at the identity warp
    sd = np.stack([Lx, Lx * ex, Lx * ey] + ([Ly] if shift_y else []), axis=1)  # (n, k, m)
    k = sd.shape[1]
    # project out the radiometric offset (the mean) and gain (the template itself)
    Lc = L - L.mean(axis=1, keepdims=True)
    Lc2 = np.maximum(np.sum(Lc * Lc, axis=1), 1e-12)
    sd, N = _projected_normal_equations(sd, Lc, ridge=1e-9)
    ok = np.abs(np.linalg.det(N)) > 0  # a flat template has no geometry to fit
    Ninv = np.zeros_like(N)
    Ninv[ok] = np.linalg.inv(N[ok])
    step_of = (Ninv.astype(np.float32) @ sd)  # (n, k, m): increment = gain · step_of @ right window
    corners_gradients = prepared if prepared is not None else least_squares_image(right)
    corners = corners_gradients[0]
    base = np.asarray(xy_right, dtype=float)
    pixel = np.floor(base)
    frac = base - pixel
    # the warp from window offsets to right-image offsets from ``base``: x' = a0 + s·dx + t·dy, y' = b0 + dy
    s = np.broadcast_to(np.asarray(initial_scale, dtype=float), (n,)).copy()
    t = np.broadcast_to(np.asarray(initial_shear, dtype=float), (n,)).copy()
    s_start, t_start = s.copy(), t.copy()
    a0, b0 = np.zeros(n), np.zeros(n)
    active = ok.copy()
    R_all = np.zeros((n, m), np.float32)  # each point's right window at its last iteration
    running = np.nonzero(ok)[0]
    for it in range(iterations):
        if len(running) == 0:
            break
        lx = ((frac[running, 0] + a0[running]).astype(np.float32)[:, None] + s[running, None].astype(np.float32) * ex
              + t[running, None].astype(np.float32) * ey)
        ly = (frac[running, 1] + b0[running]).astype(np.float32)[:, None] + ey
        Rv = _sample_windows(corners, pixel[running], lx, ly)
        Rc = Rv - Rv.mean(axis=1, keepdims=True)
        gain = np.sum(Rc * Lc[running], axis=1) / np.maximum(np.sum(Rc * Rc, axis=1), 1e-12)
        # the projected steepest-descent images are orthogonal to the offset and the template, so the residual
        # gain·R + offset - L reduces to gain·R
        d = (step_of[running] @ Rv[..., None])[..., 0].astype(float) * gain[:, None]
        d0, d1, d2 = d[:, 0], d[:, 1], d[:, 2]
        db = d[:, 3] if shift_y else np.zeros(len(running))
        ds = 1.0 + d1
        sr, tr = s[running], t[running]
        # W <- W o W(d)^-1, all in the group x' = a0 + s·dx + t·dy, y' = b0 + dy
        shift = -(sr * (d0 - d2 * db) / ds + tr * db)
        s[running] = sr / ds
        t[running] = tr - sr * d2 / ds
        a0[running] += shift
        b0[running] -= db
        # a step larger than a pixel means the window slid off the match
        slid = (np.abs(shift) >= 1.0) | ~(ds > 0.1)
        active[running[slid]] = False
        # points whose shift no longer changes stop iterating (the others go on)
        go_on = ~slid & ((np.abs(shift) >= 1e-3) | (np.abs(db) >= 1e-3))
        stop = ~go_on if it < iterations - 1 else np.ones(len(running), bool)
        R_all[running[stop]] = Rv[stop]
        running = running[go_on]
    Rc = R_all - R_all.mean(axis=1, keepdims=True)
    gain = np.sum(Rc * Lc, axis=1) / np.maximum(np.sum(Rc * Rc, axis=1), 1e-12)
    resid = gain[:, None] * Rc - Lc
    s0 = np.sqrt(np.sum(resid * resid, axis=1) / (m - k - 2))
    # the x shift's precision from the right window's own gradients at the solution, as the forward adjustment
    # (Gruen's) has it: the template's gradients, differenced at the left image's pixel spacing, understate a
    # squeezed window's and overstate a stretched one's (paper scale, stretch 1.5 and more: 1.27x the forward
    # sigma, fewer matches accepted). The gain and offset projected out as above
    x = base[:, 0, None] + a0[:, None] + s[:, None] * ex + t[:, None] * ey
    y = base[:, 1, None] + b0[:, None] + ey
    g = sample_bilinear(corners_gradients[1], x, y) * gain[:, None, None].astype(np.float32)
    gx, gy = g[..., 0], g[..., 1]
    sd = np.stack([gx, gx * ex, gx * ey] + ([gy] if shift_y else []), axis=1)
    _, N = _projected_normal_equations(sd, Rc, ridge=1e-12)
    fine = np.abs(np.linalg.det(N)) > 0
    var = np.full(n, np.inf)
    var[fine] = np.linalg.inv(N[fine])[:, 0, 0]
    sigma = s0 * np.sqrt(np.abs(var))
    rho = np.sum(Rc * Lc, axis=1) / np.maximum(np.sqrt(np.sum(Rc * Rc, axis=1) * Lc2), 1e-12)
    # the shape may change from its start (the correlation's stretch and shear) by this much, no more
    converged = (active & (np.hypot(a0, b0) < 1.5) & (np.abs(s - s_start) < 0.6) & (np.abs(t - t_start) < 0.5)
                 & (gain > 0.2))
    out = {"xy": base + np.column_stack([a0, b0]), "sigma": sigma, "rho": rho, "converged": converged}
    if antialias_px > 0 and _again:
        # the template's blur followed the starting stretch; where the solved one asks for a clearly different blur
        # (a guessed start, or a plane's noise on unsqueezed skin) the point is solved again from there with it
        redo = np.nonzero(converged & (np.abs(_antialias_sigma(s, antialias_px)
                                               - _antialias_sigma(s_start, antialias_px)) > 0.1))[0]
        if len(redo):
            again = least_squares_refine(left, right, xy_left[redo], out["xy"][redo], window, iterations, shift_y,
                                         s[redo], t[redo], corners_gradients, antialias_px, _again=False)
            for key in out:
                out[key][redo] = again[key]
    return out
