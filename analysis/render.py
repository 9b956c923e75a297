"""Shaded surfaces drawn without a GPU: triangles projected orthographically and rasterised in numpy.

A view looks at the torso along one of the patient frame's axes (``back``: from
behind, ``front``, ``side``: at the patient's right side, ``top``: down from
above). Every triangle of the surface is projected to the picture, the pixels
whose centres it covers found in one vectorised pass per size class (no loop
over triangles) and the nearest triangle kept at each pixel (a z-buffer). Each
covered pixel gets its triangle's interpolated normal, Lambert-shaded by a light
over the viewer's left shoulder (two-sided: a triangle wound either way is lit
as facing the viewer), and any per-vertex value interpolated.

The surface is the reconstruction's triangle mesh when there is one, or a
triangulation of the points that face the camera (a 2.5-D Delaunay in the
view's plane, long edges dropped: the cloud is a height field seen from there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LIGHT = np.array([-0.3, 0.35, 1.0])  # screen right, up, towards the viewer: over the viewer's left shoulder
AMBIENT = 0.35


@dataclass
class Surface:
    """Triangles ``faces`` (F, 3) over ``points`` (N, 3, rig frame, mm) with unit vertex ``normals`` (N, 3);
    ``index`` (N,): the source point of each vertex (a cloud's surface), None for a mesh's own vertices."""

    points: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    index: np.ndarray | None = None


def view_basis(frame, view: str) -> np.ndarray:
    """Rows: the picture's right, its up and the direction towards the viewer (rig frame, unit)."""
    left, post, up = frame.R
    towards = {"back": post, "front": -post, "side": -left, "top": up}[view]
    pic_up = post if view == "top" else up
    return np.vstack([np.cross(pic_up, towards), pic_up, towards])


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals of a triangle mesh (their sign follows the winding)."""
    a, b, c = (points[faces[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)
    n = np.zeros_like(points, dtype=float)
    for k in range(3):
        for j in range(3):
            n[:, j] += np.bincount(faces[:, k], fn[:, j], minlength=len(points))
    length = np.linalg.norm(n, axis=1)
    return n / np.where(length > 0, length, 1.0)[:, None]


def mesh_surface(points, faces) -> Surface:
    points = np.asarray(points, float)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    return Surface(points, faces, vertex_normals(points, faces))


def face_normals(surface: Surface) -> np.ndarray:
    a, b, c = (surface.points[surface.faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return n / np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]


def front_faces(surface: Surface, towards: np.ndarray, normals: np.ndarray | None = None) -> Surface:
    """The surface without its triangles turned away from the viewer (a mesh wound outwards): through a hole
    in the skin the viewer sees what lies behind it, not the inside of the far side."""
    n = face_normals(surface) if normals is None else normals
    return Surface(surface.points, surface.faces[n @ towards > 0.0], surface.normals, surface.index)


def combine(first: Surface, second: Surface) -> Surface:
    """Both surfaces' triangles in one (their vertices' ``index`` kept where both have one)."""
    index = None
    if first.index is not None and second.index is not None:
        index = np.concatenate([first.index, second.index])
    return Surface(np.vstack([first.points, second.points]),
                   np.vstack([first.faces, second.faces + len(first.points)]),
                   np.vstack([first.normals, second.normals]), index)


def point_spacing(points: np.ndarray) -> float:
    """The cloud's sampling spacing (mm): clustered samples count as sparse as they are."""
    from .torso import spacings

    nearest, sampling = spacings(points)
    return max(nearest, sampling)


def facing_surface(points, normals, basis: np.ndarray, max_edge_mm: float, fill: bool = True) -> Surface:
    """A surface over the points of a cloud that face the viewer of ``basis``: their Delaunay triangulation in
    the picture's plane, triangles with an edge longer than ``max_edge_mm`` (in 3-D) dropped; ``fill``: with a
    small square behind each point those left alone."""
    from scipy.spatial import Delaunay

    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    keep = np.nonzero(normals @ basis[2] > -0.05)[0]
    empty = Surface(points[:0], np.zeros((0, 3), np.int64), normals[:0], np.zeros(0, np.int64))
    if len(keep) < 3:
        return empty
    P, N = points[keep], normals[keep]
    try:
        tri = Delaunay(P @ basis[:2].T).simplices.astype(np.int64)
    except Exception:  # noqa: BLE001 - a degenerate set (all on a line): nothing to draw
        return empty
    a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    longest = np.maximum(np.maximum(np.linalg.norm(a - b, axis=1), np.linalg.norm(b - c, axis=1)),
                         np.linalg.norm(c - a, axis=1))
    good = longest <= max_edge_mm
    if not fill:
        return Surface(P, tri[good], N, keep)
    # behind the triangles, a small square facing the viewer at each point a dropped triangle touched (or none
    # kept): it fills the holes left where two parts overlap in the picture (an arm before the flank), and
    # never covers a triangle
    lone = np.ones(len(P), bool)
    lone[tri[good].ravel()] = False
    lone[tri[~good].ravel()] = True
    j = np.nonzero(lone)[0]
    h = 0.2 * max_edge_mm
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * h
    sq = (P[j, None, :] + corners @ basis[:2] - 0.5 * max_edge_mm * basis[2]).reshape(-1, 3)
    base = len(P) + 4 * np.arange(len(j))[:, None]
    quads = np.vstack([base + np.array([0, 1, 2]), base + np.array([0, 2, 3])])
    return Surface(np.vstack([P, sq]), np.vstack([tri[good], quads]), np.vstack([N, np.repeat(N[j], 4, axis=0)]),
                   np.concatenate([keep, np.repeat(keep[j], 4)]))


@dataclass
class Placement:
    """Picture pixel = ``centre_px + scale * (screen mm - centre_mm)`` (rows grow downwards)."""

    basis: np.ndarray
    scale: float  # px per mm
    centre_mm: np.ndarray  # (2,) screen mm at the picture's centre
    width: int
    height: int

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2: column, row; continuous, pixel centres at +0.5) and depth towards the viewer."""
        q = np.asarray(points, float).reshape(-1, 3) @ self.basis.T
        col = 0.5 * self.width + self.scale * (q[:, 0] - self.centre_mm[0])
        row = 0.5 * self.height - self.scale * (q[:, 1] - self.centre_mm[1])
        return np.column_stack([col, row]), q[:, 2]


def place(points, basis: np.ndarray, width: int, height: int, margin: float = 0.06, within=None,
          spare=(0.3, 0.12)) -> Placement:
    """The projection that fits ``points`` into a ``width`` x ``height`` picture with a margin on each side.

    ``within``: points that must be seen whole (e.g. the trunk): the picture then holds ``points`` only as far
    as ``spare`` (a fraction of their width across, of their height up and down) beyond them."""
    q = np.asarray(points, float).reshape(-1, 3) @ basis[:2].T
    if len(q) == 0:
        return Placement(basis, 1.0, np.zeros(2), width, height)
    lo, hi = q.min(axis=0), q.max(axis=0)
    if within is not None and len(within) > 2:
        w = np.asarray(within, float).reshape(-1, 3) @ basis[:2].T
        wlo, whi = w.min(axis=0), w.max(axis=0)
        pad = np.array(spare) * (whi - wlo)
        lo, hi = np.maximum(np.minimum(lo, wlo), wlo - pad), np.minimum(np.maximum(hi, whi), whi + pad)
    span = np.maximum(hi - lo, 1.0)
    scale = min(width * (1 - 2 * margin) / span[0], height * (1 - 2 * margin) / span[1])
    return Placement(basis, float(scale), 0.5 * (lo + hi), width, height)


def _expand(counts: np.ndarray):
    """For runs of ``counts``: each element's run index and its position within the run."""
    run = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
    starts = (np.cumsum(counts) - counts).astype(np.int32)
    return run, np.arange(int(counts.sum()), dtype=np.int32) - starts[run]


def rasterise(xy: np.ndarray, depth: np.ndarray, faces: np.ndarray, width: int, height: int):
    """Which triangle is nearest the viewer at each pixel: ``(tri (H, W) int, -1 where none, depth (H, W))``.

    ``xy``: vertices' pixel coordinates (column, row), ``depth``: towards the viewer (larger is nearer).
    Scanlines, all triangles at once: each triangle's rows of pixel centres, each row's span between the
    triangle's edges, every pixel of every span, and at each pixel the nearest (a z-buffer by ``maximum.at``).
    """
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    tri_buf = np.full(height * width, -1, np.int64)
    z_buf = np.full(height * width, -np.inf, np.float32)
    X, Y, Z = xy[faces, 0], xy[faces, 1], depth[faces]  # (F, 3)
    area = (X[:, 1] - X[:, 0]) * (Y[:, 2] - Y[:, 0]) - (X[:, 2] - X[:, 0]) * (Y[:, 1] - Y[:, 0])
    r0 = np.maximum(np.ceil(Y.min(axis=1) - 0.5), 0)
    r1 = np.minimum(np.floor(Y.max(axis=1) - 0.5), height - 1)
    ok = (r1 >= r0) & (np.abs(area) > 1e-12) & np.isfinite(Z).all(axis=1) & np.isfinite(X).all(axis=1) & \
        (X.max(axis=1) >= 0) & (X.min(axis=1) <= width)
    sel = np.nonzero(ok)[0]
    if len(sel) == 0:
        return tri_buf.reshape(height, width), z_buf.reshape(height, width)
    X, Y, Z, area, r0 = X[sel], Y[sel], Z[sel], area[sel], r0[sel].astype(np.int64)
    # the depth's plane over each triangle: z = Z0 + gx (x - X0) + gy (y - Y0)
    gx = ((Z[:, 1] - Z[:, 0]) * (Y[:, 2] - Y[:, 0]) - (Z[:, 2] - Z[:, 0]) * (Y[:, 1] - Y[:, 0])) / area
    gy = ((X[:, 1] - X[:, 0]) * (Z[:, 2] - Z[:, 0]) - (X[:, 2] - X[:, 0]) * (Z[:, 1] - Z[:, 0])) / area
    z_at0 = Z[:, 0] - gx * X[:, 0] - gy * Y[:, 0]  # the plane's depth at pixel coordinates (0, 0)
    t, k = _expand((r1[sel].astype(np.int64) - r0 + 1))
    row = r0[t] + k
    yc = row + 0.5
    # each edge's crossing of the row's centre line; the span runs between the crossings
    lo = np.full(len(t), np.inf)
    hi = np.full(len(t), -np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        xi, yi, xj, yj = X[t, i], Y[t, i], X[t, j], Y[t, j]
        dy = yj - yi
        crosses = (np.minimum(yi, yj) <= yc) & (yc <= np.maximum(yi, yj)) & (dy != 0)
        x = xi + (yc - yi) * (xj - xi) / np.where(dy != 0, dy, 1.0)
        lo = np.where(crosses, np.minimum(lo, x), lo)
        hi = np.where(crosses, np.maximum(hi, x), hi)
    c0 = np.maximum(np.ceil(lo - 0.5 - 1e-6), 0)
    c1 = np.minimum(np.floor(hi - 0.5 + 1e-6), width - 1)
    n = np.where(np.isfinite(c0) & np.isfinite(c1) & (c1 >= c0), c1 - c0 + 1, 0).astype(np.int64)
    c0 = np.where(n > 0, c0, 0).astype(np.int64)
    # per span: the depth at its first pixel, the step along the row, the first pixel's index, the triangle
    z_first = z_at0[t] + gy[t] * yc + gx[t] * (c0 + 0.5)
    span, k = _expand(n)
    z = z_first.astype(np.float32)[span] + gx[t].astype(np.float32)[span] * k.astype(np.float32)
    pix = (row * width + c0).astype(np.int32)[span] + k.astype(np.int32)
    np.maximum.at(z_buf, pix, z)
    win = z >= z_buf[pix]
    tri_buf[pix[win]] = sel[t[span[win]]]
    return tri_buf.reshape(height, width), z_buf.reshape(height, width)


@dataclass
class Rendered:
    """One view: ``tri`` (H, W) the nearest triangle (-1: background), ``depth`` (H, W), ``shade`` (H, W) in
    [0, 1] and ``value`` (H, W) the interpolated per-vertex value (NaN where none)."""

    placement: Placement
    tri: np.ndarray
    depth: np.ndarray
    shade: np.ndarray
    value: np.ndarray | None

    @property
    def covered(self) -> np.ndarray:
        return self.tri >= 0

    def visible(self, points, tolerance_mm: float = 15.0) -> np.ndarray:
        """Which of ``points`` (rig frame) the viewer sees: inside the picture and not behind the surface."""
        xy, d = self.placement.project(points)
        col, row = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
        H, W = self.tri.shape
        inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        out = np.zeros(len(xy), bool)
        k = np.nonzero(inside)[0]
        r0, r1 = np.clip(row[k] - 2, 0, H - 1), np.clip(row[k] + 2, 0, H - 1)
        c0, c1 = np.clip(col[k] - 2, 0, W - 1), np.clip(col[k] + 2, 0, W - 1)
        for i, kk in enumerate(k):  # a handful of landmarks
            near = self.depth[r0[i]:r1[i] + 1, c0[i]:c1[i] + 1]
            near = near[np.isfinite(near)]
            out[kk] = len(near) > 0 and d[kk] >= near.max() - tolerance_mm
        return out


def render(surface: Surface, placement: Placement, values=None) -> Rendered:
    """Rasterise ``surface`` as ``placement`` sees it; ``values`` (N,) or (N, k) per vertex are interpolated."""
    W, H = placement.width, placement.height
    value = None
    xy, depth = placement.project(surface.points)
    tri, zbuf = rasterise(xy, depth, surface.faces, W, H)
    shade = np.zeros((H, W))
    if values is not None:
        values = np.asarray(values, float)
        value = np.full((H, W) + values.shape[1:], np.nan)
    rows, cols = np.nonzero(tri >= 0)
    if len(rows):
        # Gouraud: each vertex lit once (two-sided: its normal turned towards the viewer), the light interpolated
        n = surface.normals @ placement.basis.T  # screen right, up, towards
        n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
        light = LIGHT / np.linalg.norm(LIGHT)
        half = light + np.array([0.0, 0.0, 1.0])
        half /= np.linalg.norm(half)
        lit = AMBIENT + (1 - AMBIENT) * np.clip(n @ light, 0.0, 1.0) + 0.12 * np.clip(n @ half, 0.0, 1.0) ** 24
        f = surface.faces[tri[rows, cols]]
        x, y = xy[f, 0], xy[f, 1]
        px, py = cols + 0.5, rows + 0.5
        area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
        w1 = ((px - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (py - y[:, 0])) / area
        w2 = ((x[:, 1] - x[:, 0]) * (py - y[:, 0]) - (px - x[:, 0]) * (y[:, 1] - y[:, 0])) / area
        w = np.clip(np.column_stack([1.0 - w1 - w2, w1, w2]), 0.0, 1.0)
        shade[rows, cols] = np.clip(np.einsum("pk,pk->p", w, lit[f]), 0.0, 1.0)
        if values is not None:
            # the vertices with a value, weighted; a pixel mostly nearer vertices without one gets none
            v = values.reshape(len(values), -1)[f]  # (p, 3, k)
            has = np.isfinite(v)
            wk = w[:, :, None] * has
            total = wk.sum(axis=1)
            value[rows, cols] = (np.where(total >= 0.5, (wk * np.where(has, v, 0.0)).sum(axis=1) /
                                          np.maximum(total, 1e-12), np.nan)).reshape(value[rows, cols].shape)
    return Rendered(placement, tri, zbuf, shade, value)


def compose(rendered: Rendered, colours: np.ndarray, background=(255, 255, 255)) -> np.ndarray:
    """An RGBA picture (H, W, 4, uint8) from the per-pixel base ``colours`` (H, W, 3, in [0, 1]) shaded; the
    background transparent."""
    H, W = rendered.tri.shape
    img = np.zeros((H, W, 4), np.uint8)
    img[..., :3] = background
    cov = rendered.covered
    lit = np.asarray(colours)[cov] * rendered.shade[cov, None]
    img[cov, :3] = np.clip(lit * 255.0 + 0.5, 0, 255).astype(np.uint8)
    img[cov, 3] = 255
    return img
