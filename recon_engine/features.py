"""Region of interest and Harris features.

The region of interest is where the projected pattern lights the subject:
there the local contrast is high. The background, which the projectors
do not reach, and the subject's cast shadows have low contrast and are not
searched. A user-drawn polygon per image can narrow it further.

Features are Harris corners of the (rectified) image inside the region of
interest: non-maximum suppression over the minimum spacing, a relative
response threshold, and a subpixel position from a quadratic fit of the
response around each maximum.
"""

from __future__ import annotations

import cv2
import numpy as np


def local_contrast(image: np.ndarray, window: int) -> np.ndarray:
    """Standard deviation of the grey values over a ``window``-square neighbourhood (grey levels)."""
    img = np.asarray(image, dtype=np.float32)
    m = cv2.boxFilter(img, cv2.CV_32F, (window, window), borderType=cv2.BORDER_REFLECT)
    m2 = cv2.boxFilter(np.square(img), cv2.CV_32F, (window, window), borderType=cv2.BORDER_REFLECT)
    # in place: a paper-scale image is 24 MB per float32 array, and two arms run this at once
    np.square(m, out=m)
    np.subtract(m2, m, out=m2)
    np.maximum(m2, 0, out=m2)
    return np.sqrt(m2, out=m2)


def blur_sigma(image: np.ndarray, reblur_px: float = 2.0, edge_share: float = 0.1) -> float:
    """An image's blur (px, as a Gaussian's sigma) from how much a known extra blur lowers its edges' gradients.

    At a step edge blurred by sigma the gradient's peak is proportional to
    1 / sigma; blurring the image again by ``reblur_px`` lowers it by
    R = sqrt(sigma² + reblur_px²) / sigma, so sigma = reblur_px / sqrt(R² − 1)
    (the re-blur estimate of Zhuo & Sim 2011). Taken at the gradient's local
    maxima among the strongest ``edge_share`` of the pixels; the median over
    them. It is not the true blur: the gradient operator's own smoothing and
    neighbouring edges (the projected pattern's cells are a few pixels wide)
    bias it, up for sharp isolated steps, down for the pattern. It orders
    images by blur and is compared with thresholds measured the same way
    (``MatchingConfig.blurred_above_px``).
    """
    img = np.asarray(image, dtype=np.float32)

    def gradient(a):
        return cv2.magnitude(cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3))

    g = gradient(img)
    g_reblurred = gradient(cv2.GaussianBlur(img, (0, 0), reblur_px))
    peak = (g >= cv2.dilate(g, np.ones((3, 3), np.uint8))) & (g > np.percentile(g[::4, ::4], 100 * (1 - edge_share)))
    ratio = g[peak] / np.maximum(g_reblurred[peak], 1e-6)
    ratio = ratio[ratio > 1.001]  # flat or saturated pixels the extra blur did not lower
    if len(ratio) == 0:
        return float("nan")
    return float(reblur_px / np.sqrt(np.median(ratio) ** 2 - 1.0))


def region_of_interest(image: np.ndarray, window: int = 15, min_contrast: float | None = None,
                       min_area_px: int | None = None, polygon=None) -> np.ndarray:
    """Boolean mask of the pattern-lit subject in ``image``.

    Parameters
    ----------
    image : (H, W) array
        Grey image (any dtype; 8-bit levels assumed for the defaults).
    window : int
        Side (px) of the neighbourhood of the contrast measure; a few pattern
        cells wide.
    min_contrast : float, optional
        Standard deviation (grey levels) below which a pixel is not lit by the
        pattern. Default: a third of the 95th percentile of the image's
        contrast, and at least 4 levels (well above sensor noise).
    min_area_px : int, optional
        Connected parts smaller than this are dropped (specular spots, the
        test field's edge); default 2% of the largest part.
    polygon : (K, 2) array, optional
        A user-drawn outline (px, the image's own coordinates); only its
        inside is kept.
    """
    c = local_contrast(image, window)
    if min_contrast is None:
        min_contrast = max(4.0, float(np.percentile(c, 95)) / 3.0)
    mask = (c >= min_contrast).astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (window, window))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, k)
    # erode half a window: the contrast window smears the lit border outwards
    mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (window // 2 * 2 + 1,) * 2))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n > 1:
        areas = stats[1:, cv2.CC_STAT_AREA]
        floor = min_area_px if min_area_px is not None else 0.02 * areas.max()
        keep = np.zeros(n, dtype=bool)
        keep[1:] = areas >= floor
        mask = keep[labels].astype(np.uint8)
    if polygon is not None:
        poly = np.zeros_like(mask)
        cv2.fillPoly(poly, [np.round(np.asarray(polygon, dtype=float)).astype(np.int32).reshape(-1, 1, 2)], 1)
        mask &= poly
    return mask.astype(bool)


STRIP_ROWS = 256  # rows of an image whose structure tensor OpenCV holds at once (corner_response_in_strips)


def corner_response_in_strips(corner_fn, image: np.ndarray, block_size: int, ksize: int, *args) -> np.ndarray:
    """``corner_fn(image, block_size, ksize, *args)`` (OpenCV's cornerHarris or cornerMinEigenVal) of a grey
    image, computed over strips of ``STRIP_ROWS`` rows, each with enough rows above and below for its
    derivatives and window, so every pixel sees the neighbours it would in the whole image.

    Why: OpenCV holds the derivatives and the three-channel structure tensor of the whole image meanwhile,
    about six times the response (143 MB for one 3000 x 2000 px image), and two arms run this at once.
    """
    img = np.asarray(image, dtype=np.float32)
    H = img.shape[0]
    if H <= 2 * STRIP_ROWS:
        return corner_fn(img, block_size, ksize, *args)
    margin = block_size // 2 + ksize // 2 + 2
    out = np.empty(img.shape, np.float32)
    for r0 in range(0, H, STRIP_ROWS):
        r1 = min(H, r0 + STRIP_ROWS)
        a, b = max(0, r0 - margin), min(H, r1 + margin)
        out[r0:r1] = corner_fn(img[a:b], block_size, ksize, *args)[r0 - a:r1 - a]
    return out


def harris_response(image: np.ndarray, block_size: int = 5, ksize: int = 3, k: float = 0.04) -> np.ndarray:
    """OpenCV's Harris corner response of a grey image (float32)."""
    return corner_response_in_strips(cv2.cornerHarris, image, block_size, ksize, k)


def harris_features(image: np.ndarray, mask: np.ndarray | None = None, spacing: int = 6,
                    relative_threshold: float = 0.01, block_size: int = 5, max_features: int | None = None):
    """Harris corners inside ``mask``, at least ``spacing`` px apart.

    Parameters
    ----------
    image : (H, W) array
        Grey image.
    mask : (H, W) bool array, optional
        Region of interest; features only where it is true.
    spacing : int
        Minimum distance (px, Chebyshev) between two features: the density
        parameter (one feature per ``spacing``² px at most).
    relative_threshold : float
        Responses below this fraction of the 99th percentile response are not
        corners.
    block_size : int
        Neighbourhood (px) of the structure tensor.
    max_features : int, optional
        Keep only the strongest this many.

    Returns ``(xy, response)``: subpixel positions (N, 2) px (x = column,
    y = row) and their Harris responses (N,), strongest first.
    """
    R = harris_response(image, block_size)
    if mask is not None:
        R[~np.asarray(mask, dtype=bool)] = 0  # R is our own array: no copy of a full-size image
    positive = R[R > 0]
    if positive.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    floor = relative_threshold * float(np.percentile(positive, 99))
    size = 2 * (spacing // 2) + 1
    peak = (R == cv2.dilate(R, np.ones((size, size), np.uint8))) & (R > floor)
    # not on the outermost row/column: the quadratic fit needs neighbours
    peak[[0, -1], :] = False
    peak[:, [0, -1]] = False
    rows, cols = np.nonzero(peak)
    # plateaus give several equal maxima: keep one per spacing cell
    cell = (rows // max(spacing, 1)) * (R.shape[1] // max(spacing, 1) + 1) + cols // max(spacing, 1)
    resp = R[rows, cols]
    order = np.lexsort((-resp, cell))
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    sel = order[first]
    rows, cols, resp = rows[sel], cols[sel], resp[sel]
    # subpixel: a parabola through the response along each axis
    c0 = R[rows, cols]
    dx = 0.5 * (R[rows, cols + 1] - R[rows, cols - 1])
    dxx = R[rows, cols + 1] - 2 * c0 + R[rows, cols - 1]
    dy = 0.5 * (R[rows + 1, cols] - R[rows - 1, cols])
    dyy = R[rows + 1, cols] - 2 * c0 + R[rows - 1, cols]
    ox = np.where(dxx < 0, -dx / np.where(dxx < 0, dxx, -1), 0)
    oy = np.where(dyy < 0, -dy / np.where(dyy < 0, dyy, -1), 0)
    xy = np.column_stack([cols + np.clip(ox, -0.5, 0.5), rows + np.clip(oy, -0.5, 0.5)])
    order = np.argsort(-resp, kind="stable")
    if max_features is not None:
        order = order[:max_features]
    return xy[order], resp[order]


def cell_features(image: np.ndarray, mask: np.ndarray, cell: int, taken: np.ndarray | None = None,
                  relative_threshold: float = 0.05, block_size: int = 5) -> np.ndarray:
    """One point per ``cell`` x ``cell`` px cell of ``mask``: its best-textured pixel, where no feature is ``taken``.

    Between the corners of a projected pattern the skin is still textured (the
    edges of its dots), but Harris finds no peak there: where the pattern's
    corners are sparser than the pixels (a camera coarser than the pattern's
    design), these points let matching follow the pixels rather than the
    corners. Texture is the smaller eigenvalue of the structure tensor over
    ``block_size`` px (Shi-Tomasi); cells whose best is below
    ``relative_threshold`` of the 99th percentile get no point.

    Returns integer positions (N, 2) px (x = column, y = row), best-textured first.
    """
    E = corner_response_in_strips(cv2.cornerMinEigenVal, image, block_size, 3)
    E[~np.asarray(mask, dtype=bool)] = 0  # E is our own array, as harris_features' R
    positive = E[E > 0]
    if positive.size == 0 or cell < 1:
        return np.zeros((0, 2))
    floor = relative_threshold * float(np.percentile(positive, 99))
    H, W = (E.shape[0] // cell) * cell, (E.shape[1] // cell) * cell
    blocks = E[:H, :W].reshape(H // cell, cell, W // cell, cell).transpose(0, 2, 1, 3).reshape(H // cell, W // cell, -1)
    best = blocks.argmax(axis=2)
    value = np.take_along_axis(blocks, best[..., None], axis=2)[..., 0]
    free = value > floor
    if taken is not None and len(taken):
        t = np.floor(np.asarray(taken, float)).astype(int)
        inside = (t[:, 0] >= 0) & (t[:, 0] < W) & (t[:, 1] >= 0) & (t[:, 1] < H)
        free[t[inside, 1] // cell, t[inside, 0] // cell] = False
    # not on the image's outermost pixels (matching windows need their neighbours)
    gy, gx = np.nonzero(free)
    y = gy * cell + best[gy, gx] // cell
    x = gx * cell + best[gy, gx] % cell
    ok = (x > 0) & (y > 0) & (x < E.shape[1] - 1) & (y < E.shape[0] - 1)
    order = np.argsort(-value[gy, gx][ok], kind="stable")
    return np.column_stack([x[ok], y[ok]]).astype(float)[order]
