"""Compiled inner loops of the matching stage (numba), one point at a time.

Correlating a window along a row and least-squares matching are a few
thousand multiply-adds per point on windows of a few dozen pixels: as numpy
array operations over blocks of points they pass over memory dozens of
times per point. Here each point's window stays in registers and cache, the
interpolation is exact bilinear (not OpenCV's 1/32-px steps), and the loops
release the GIL so that the matching's threads run them side by side. A
point's result depends on that point alone, whatever block or thread it is
computed in.

Compiled on first use and cached beside this file (numba's ``cache=True``).
Pixel coordinates follow OpenCV's convention: (x = column, y = row), the
centre of the top-left pixel at (0, 0); pixels outside an image count as 0.
"""

from __future__ import annotations

from math import floor, sqrt

import numba
import numpy as np

_JIT = dict(nogil=True, cache=True, fastmath={"contract"})


@numba.njit(inline="always", **_JIT)
def _pixel(image, ix, iy):
    h, w = image.shape
    if 0 <= ix < w and 0 <= iy < h:
        return image[iy, ix]
    return 0.0


@numba.njit(inline="always", **_JIT)
def bilinear(image, x, y):
    """Exact bilinear sample of ``image`` at (x, y) px; pixels outside count as 0."""
    fx0, fy0 = floor(x), floor(y)
    fx, fy = x - fx0, y - fy0
    ix, iy = int(fx0), int(fy0)
    h, w = image.shape
    if 0 <= ix < w - 1 and 0 <= iy < h - 1:
        a, b = image[iy, ix], image[iy, ix + 1]
        c, d = image[iy + 1, ix], image[iy + 1, ix + 1]
    else:
        a, b = _pixel(image, ix, iy), _pixel(image, ix + 1, iy)
        c, d = _pixel(image, ix, iy + 1), _pixel(image, ix + 1, iy + 1)
    top = a + fx * (b - a)
    return top + fy * (c + fx * (d - c) - top)


@numba.njit(inline="always", **_JIT)
def _sample_row(image, x_first, step, y, out, row):
    """``out[row, c]`` = samples of ``image`` at (x_first + step·c, y) for every column c of ``out``."""
    h, w = image.shape
    n = out.shape[1]
    fy0 = floor(y)
    iy = int(fy0)
    fy = y - fy0
    x_last = x_first + step * (n - 1)
    if 0 <= iy < h - 1 and 0 <= min(x_first, x_last) and max(x_first, x_last) < w - 1:
        for c in range(n):  # the whole row inside: no border checks
            x = x_first + step * c
            fx0 = floor(x)
            ix = int(fx0)
            fx = x - fx0
            a, b = image[iy, ix], image[iy, ix + 1]
            cc, d = image[iy + 1, ix], image[iy + 1, ix + 1]
            top = a + fx * (b - a)
            out[row, c] = top + fy * (cc + fx * (d - cc) - top)
    else:
        for c in range(n):
            out[row, c] = bilinear(image, x_first + step * c, y)


@numba.njit(inline="always", **_JIT)
def _parabola(m, l, r):
    """Subpixel offset (px, within ±0.5) of a peak ``m`` between its neighbours ``l`` and ``r``."""
    den = l - 2.0 * m + r
    off = 0.5 * (l - r) / den if den < 0 else 0.0
    return min(max(off, -0.5), 0.5)


@numba.njit(**_JIT)
def ncc_points(left, right, xy, x_centre, scale, shear, radius, band, window, exclude):
    """Normalized cross-correlation search of each left point along its row of the right image.

    For point p the left window (``window`` px square around ``xy[p]``) is
    compared with the right windows centred at column ``x_centre[p] +
    scale[p]·c + shear[p]·r`` of row ``xy[p, 1] + r``, for c in
    −``radius``..``radius`` and r in −``band``..``band`` (whole px); each right
    window's columns are ``scale[p]`` px apart and shift by ``shear[p]`` px
    per row, as a surface patch foreshortened differently in the two views
    appears. Returns ``(xy_right (N, 2), best (N,),
    second (N,), at_edge (N,))``: the subpixel peak (parabola fits across
    columns and rows), its correlation, the best correlation at least
    ``exclude`` columns away (any row; −1 if none), and whether the peak
    lies on the first or last column searched.
    """
    n = xy.shape[0]
    h = window // 2
    B, D = 2 * band + 1, 2 * radius + 1
    R, C = B + window - 1, D + window - 1
    m = window * window
    out = np.empty((n, 2))
    best_out = np.empty(n)
    second_out = np.empty(n)
    edge = np.empty(n, np.bool_)
    L = np.empty((window, window))
    S = np.empty((R, C))
    col1 = np.empty((B, C))
    col2 = np.empty((B, C))
    num = np.empty((B, D))
    ncc = np.empty((B, D))
    for p in range(n):
        px, py = xy[p, 0], xy[p, 1]
        for i in range(window):
            _sample_row(left, px - h, 1.0, py + (i - h), L, i)
        mean = 0.0
        for i in range(window):
            for j in range(window):
                mean += L[i, j]
        mean /= m
        lnorm = 0.0
        for i in range(window):
            for j in range(window):
                L[i, j] -= mean
                lnorm += L[i, j] * L[i, j]
        lnorm = sqrt(lnorm)
        sc, sh, xc = scale[p], shear[p], x_centre[p]
        for r in range(R):
            dy = r - band - h
            _sample_row(right, xc + sh * dy - sc * (radius + h), sc, py + dy, S, r)
        # the strip made mean-free: the window sums of its squares then lose nothing to cancellation
        mean = 0.0
        for r in range(R):
            for c in range(C):
                mean += S[r, c]
        mean /= R * C
        for r in range(R):
            for c in range(C):
                S[r, c] -= mean
        # window sums of the strip and of its squares: sums down the window's rows, then along the row
        for b in range(B):
            for c in range(C):
                a1 = 0.0
                a2 = 0.0
                for i in range(window):
                    v = S[b + i, c]
                    a1 += v
                    a2 += v * v
                col1[b, c] = a1
                col2[b, c] = a2
        num[:] = 0.0
        for i in range(window):
            for j in range(window):
                lv = L[i, j]
                for b in range(B):
                    for d in range(D):
                        num[b, d] += S[b + i, d + j] * lv
        kb, kd, best = 0, 0, -2.0
        for b in range(B):
            for d in range(D):
                s1 = 0.0
                s2 = 0.0
                for j in range(window):
                    s1 += col1[b, d + j]
                    s2 += col2[b, d + j]
                den = lnorm * sqrt(max(s2 - s1 * s1 / m, 0.0))
                v = num[b, d] / den if den > 1e-6 else -1.0
                ncc[b, d] = v
                if v > best:  # the first of equal peaks, rows first (as numpy's argmax)
                    best, kb, kd = v, b, d
        second = -1.0
        for d in range(D):
            if abs(d - kd) > exclude:
                for b in range(B):
                    second = max(second, ncc[b, d])
        at_edge = kd == 0 or kd == D - 1
        dx = 0.0 if at_edge else _parabola(best, ncc[kb, kd - 1], ncc[kb, kd + 1])
        dy = _parabola(best, ncc[kb - 1, kd], ncc[kb + 1, kd]) if 0 < kb < B - 1 else 0.0
        out[p, 0] = xc + sc * (kd + dx - radius) + sh * (kb + dy - band)
        out[p, 1] = py - band + kb + dy
        best_out[p] = best
        second_out[p] = second
        edge[p] = at_edge
    return out, best_out, second_out, edge


@numba.njit(inline="always", **_JIT)
def _invert(N, k, inv):
    """``inv`` = inverse of the k×k matrix ``N`` (Gauss-Jordan, partial pivoting); returns det(N) (0: singular)."""
    a = N[:k, :k].copy()
    for i in range(k):
        for j in range(k):
            inv[i, j] = 1.0 if i == j else 0.0
    det = 1.0
    for col in range(k):
        piv = col
        for r in range(col + 1, k):
            if abs(a[r, col]) > abs(a[piv, col]):
                piv = r
        if a[piv, col] == 0.0:
            return 0.0
        if piv != col:
            det = -det
            for j in range(k):
                a[col, j], a[piv, j] = a[piv, j], a[col, j]
                inv[col, j], inv[piv, j] = inv[piv, j], inv[col, j]
        p = a[col, col]
        det *= p
        for j in range(k):
            a[col, j] /= p
            inv[col, j] /= p
        for r in range(k):
            if r != col and a[r, col] != 0.0:
                f = a[r, col]
                for j in range(k):
                    a[r, j] -= f * a[col, j]
                    inv[r, j] -= f * inv[col, j]
    return det


@numba.njit(inline="always", **_JIT)
def _projected_normals(sd, k, centred, w, msum, ridge, N):
    """Steepest-descent images ``sd[:k]`` (in place, 0 where the 0/1 weights ``w`` are 0) with a radiometric
    offset (their mean over the ``msum`` pixels of weight 1) and gain (the mean-free window ``centred``, 0 where
    ``w`` is) projected out, and ``N`` = their normal equations plus ``ridge`` times the trace on the
    diagonal."""
    m = sd.shape[1]
    c2 = 0.0
    for q in range(m):
        c2 += centred[q] * centred[q]
    c2 = max(c2, 1e-12)
    for a in range(k):
        mean = 0.0
        for q in range(m):
            mean += sd[a, q]
        mean /= msum
        dot = 0.0
        for q in range(m):
            sd[a, q] -= mean * w[q]
            dot += sd[a, q] * centred[q]
        f = dot / c2
        for q in range(m):
            sd[a, q] -= f * centred[q]
    trace = 0.0
    for a in range(k):
        for b in range(a, k):
            v = 0.0
            for q in range(m):
                v += sd[a, q] * sd[b, q]
            N[a, b] = v
            N[b, a] = v
        trace += N[a, a]
    for a in range(k):
        N[a, a] += ridge * trace


@numba.njit(inline="always", **_JIT)
def _gain(R, Lc, w, msum, centre):
    """Radiometric gain of window ``R`` (M,) against the mean-free template ``Lc``: ``(gain, Σ Rc·Lc, Σ Rc²)``
    over the ``msum`` pixels of 0/1 weight ``w`` 1, with ``Rc`` = ``R`` made mean-free there and 0 elsewhere
    (left in ``R`` with ``centre``)."""
    m = R.shape[0]
    mean = 0.0
    for q in range(m):
        mean += R[q] * w[q]
    mean /= msum
    num, rr = 0.0, 0.0
    for q in range(m):
        c = (R[q] - mean) * w[q]
        if centre:
            R[q] = c
        num += c * Lc[q]
        rr += c * c
    return num / max(rr, 1e-12), num, rr


@numba.njit(**_JIT)
def lsm_points(left, right, xy_left, xy_right, window, iterations, shift_y, initial_scale, initial_shear, blur_px,
               clip):
    """Adaptive least-squares matching of each point (see ``matching.least_squares_refine``, which documents the
    model): the inverse-compositional solution of an affine warp along the row (x shift, stretch, shear) and a
    y shift, with the radiometric gain and offset projected out, and the x shift's precision from the right
    window's gradients at the solution. Point p's template is blurred along its rows by a Gaussian of sigma
    ``blur_px[p]`` (template px, at most 3; none below 0.05): the detail of a squeezed right window. Pixels
    at or next to a grey level of ``clip`` or more (saturated: the template's, or the right window's where it
    starts) take no part; a point with more than half its window so is not converged.

    Returns ``(xy (N, 2) px, sigma (N,) px, rho (N,), converged (N,), stretch (N,), shear (N,))`` at the
    solution.
    """
    n = xy_left.shape[0]
    h = window // 2
    m = window * window
    k = 4 if shift_y else 3
    H, W = right.shape
    xy = np.empty((n, 2))
    sigma_out = np.empty(n)
    rho_out = np.empty(n)
    conv = np.empty(n, np.bool_)
    s_out = np.empty(n)
    t_out = np.empty(n)
    wide = window + 2
    most = 9  # taps either side of the widest blur kernel (3 sigma of 3 px)
    Wrow = np.empty((wide, wide + 2 * most))
    T = np.empty((wide, wide))
    g = np.empty(2 * most + 1)
    ex = np.empty(m)
    ey = np.empty(m)
    for i in range(window):
        for j in range(window):
            ex[i * window + j] = j - h
            ey[i * window + j] = i - h
    L = np.empty(m)
    Lc = np.empty(m)
    sd = np.empty((4, m))
    N = np.empty((4, 4))
    Ninv = np.empty((4, 4))
    step = np.empty((4, m))
    Rv = np.empty(m)
    R2 = Rv.reshape((window, window))  # the right window as rows (a view of Rv)
    d = np.empty(4)
    w = np.empty(m)
    for p in range(n):
        xl, yl = xy_left[p, 0], xy_left[p, 1]
        s_start, t_start = initial_scale[p], initial_shear[p]
        # the template one pixel wider than the window (for its central differences), blurred along its rows
        sig = min(blur_px[p], 3.0)
        if sig > 0.05:
            r = int(np.ceil(3.0 * sig))
            total = 0.0
            for q in range(2 * r + 1):
                g[q] = np.exp(-0.5 * ((q - r) / sig) ** 2)
                total += g[q]
            for q in range(2 * r + 1):
                g[q] /= total
            for i in range(wide):
                _sample_row(left, xl - h - 1 - r, 1.0, yl + (i - h - 1), Wrow[:, :wide + 2 * r], i)
                for j in range(wide):
                    v = 0.0
                    for q in range(2 * r + 1):
                        v += Wrow[i, j + q] * g[q]
                    T[i, j] = v
        else:
            for i in range(wide):
                _sample_row(left, xl - h - 1, 1.0, yl + (i - h - 1), T, i)
        # the right window where it starts: its saturated pixels are masked for the whole solution
        bx, by = xy_right[p, 0], xy_right[p, 1]
        for i in range(window):
            _sample_row(right, bx - s_start * h + t_start * (i - h), s_start, by + (i - h), R2, i)
        msum = 0.0
        for i in range(window):
            for j in range(window):
                q = i * window + j
                # a saturated pixel, or one whose gradient a saturated neighbour enters, takes no part; in the
                # right window its neighbours too (the window moves by up to a pixel)
                bright = max(T[i + 1, j + 1], T[i + 1, j], T[i + 1, j + 2], T[i, j + 1], T[i + 2, j + 1], R2[i, j],
                             R2[i, max(j - 1, 0)], R2[i, min(j + 1, window - 1)], R2[max(i - 1, 0), j],
                             R2[min(i + 1, window - 1), j])
                w[q] = 0.0 if bright >= clip else 1.0
                msum += w[q]
        mean = 0.0
        for i in range(window):
            for j in range(window):
                q = i * window + j
                L[q] = T[i + 1, j + 1]
                gx = 0.5 * (T[i + 1, j + 2] - T[i + 1, j]) * w[q]
                sd[0, q] = gx
                sd[1, q] = gx * ex[q]
                sd[2, q] = gx * ey[q]
                sd[3, q] = 0.5 * (T[i + 2, j + 1] - T[i, j + 1]) * w[q]
                mean += L[q] * w[q]
        msum = max(msum, 1.0)
        mean /= msum
        Lc2 = 0.0
        for q in range(m):
            Lc[q] = (L[q] - mean) * w[q]
            Lc2 += Lc[q] * Lc[q]
        Lc2 = max(Lc2, 1e-12)
        _projected_normals(sd, k, Lc, w, msum, 1e-9, N)
        # a flat template has no geometry to fit; one mostly saturated, too few pixels to trust
        ok = _invert(N, k, Ninv) != 0.0 and 2.0 * msum > m
        for a in range(k):
            for q in range(m):
                v = 0.0
                for b in range(k):
                    v += Ninv[a, b] * sd[b, q]
                step[a, q] = v
        s, t, a0, b0 = s_start, t_start, 0.0, 0.0
        active = ok
        Rv[:] = 0.0
        if ok:
            for _ in range(iterations):
                for i in range(window):  # the warped window, row by row: x = ... + s·dx + t·dy
                    _sample_row(right, bx + a0 - s * h + t * (i - h), s, by + b0 + (i - h), R2, i)
                gain = _gain(Rv, Lc, w, msum, False)[0]
                # the projected steepest-descent images are orthogonal to the offset and the template, so the
                # residual gain·R + offset − L reduces to gain·R
                for a in range(k):
                    v = 0.0
                    for q in range(m):
                        v += step[a, q] * Rv[q]
                    d[a] = v * gain
                db = d[3] if shift_y else 0.0
                ds = 1.0 + d[1]
                # W <- W o W(d)^-1, all in the group x' = a0 + s·dx + t·dy, y' = b0 + dy
                shift = -(s * (d[0] - d[2] * db) / ds + t * db)
                t = t - s * d[2] / ds
                s = s / ds
                a0 += shift
                b0 -= db
                slid = abs(shift) >= 1.0 or not ds > 0.1  # a step larger than a pixel: the window slid off
                if slid:
                    active = False
                    break
                if abs(shift) < 1e-3 and abs(db) < 1e-3:
                    break
        # the residuals and correlation at the last right window; the x shift's precision from the right
        # window's own gradients there (central differences, the image's border repeated), as the forward
        # adjustment (Gruen's) has it
        gain, num, rr = _gain(Rv, Lc, w, msum, True)
        res2 = 0.0
        for q in range(m):
            e = gain * Rv[q] - Lc[q]
            res2 += e * e
        s0 = sqrt(res2 / max(msum - k - 2, 1.0))
        for q in range(m):
            x = bx + a0 + s * ex[q] + t * ey[q]
            y = by + b0 + ey[q]
            fx0, fy0 = floor(x), floor(y)
            ix, iy = int(fx0), int(fy0)
            fx, fy = x - fx0, y - fy0
            gxs = 0.0
            gys = 0.0
            for cy in range(2):
                for cx in range(2):
                    jx, jy = ix + cx, iy + cy
                    if 0 <= jx < W and 0 <= jy < H:
                        wgt = (fx if cx else 1.0 - fx) * (fy if cy else 1.0 - fy)
                        gxs += wgt * 0.5 * (right[jy, min(jx + 1, W - 1)] - right[jy, max(jx - 1, 0)])
                        gys += wgt * 0.5 * (right[min(jy + 1, H - 1), jx] - right[max(jy - 1, 0), jx])
            gxs *= gain * w[q]
            sd[0, q] = gxs
            sd[1, q] = gxs * ex[q]
            sd[2, q] = gxs * ey[q]
            sd[3, q] = gys * gain * w[q]
        _projected_normals(sd, k, Rv, w, msum, 1e-12, N)
        var = np.inf
        if _invert(N, k, Ninv) != 0.0:
            var = abs(Ninv[0, 0])
        sigma_out[p] = s0 * sqrt(var)
        rho_out[p] = num / max(sqrt(rr * Lc2), 1e-12)
        conv[p] = (active and sqrt(a0 * a0 + b0 * b0) < 1.5 and abs(s - s_start) < 0.6 and abs(t - t_start) < 0.5
                   and gain > 0.2)
        xy[p, 0] = bx + a0
        xy[p, 1] = by + b0
        s_out[p] = s
        t_out[p] = t
    return xy, sigma_out, rho_out, conv, s_out, t_out


def warm_up() -> None:
    """Loads the compiled kernels (from numba's cache, or compiles them) with a call on a tiny image.

    A process's first call costs about 1.5 s (numba's compiler and runtime
    imported, the machine code loaded); the engine makes it on a thread
    while the images load.
    """
    img = np.zeros((32, 32), np.float32)
    one = np.ones(1)
    xy = np.full((1, 2), 16.0)
    ncc_points(img, img, xy, xy[:, 0].copy(), one, one * 0, 1, 1, 3, 1)
    lsm_points(img, img, xy, xy.copy(), 3, 1, True, one, one * 0, one * 0, np.inf)
