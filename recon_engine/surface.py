"""Point surfaces: triangulated irregular networks, normals and PLY files.

An arm's points are triangulated in the arm's viewing direction (a 2.5D
TIN: Delaunay in the image plane of a camera looking along the arm's mean
axis); triangles with long edges (across holes) or seen nearly edge-on
(steep, across depth jumps) are removed. These triangles are the patches of
point-to-patch registration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import Delaunay


@dataclass
class PointSurface:
    """Points (mm, world frame) with normals, triangular patches and per-point data.

    ``faces`` (F, 3) index ``points``; ``normals`` (N, 3) unit, pointing to the
    viewer; ``data`` holds per-point arrays (``sigma_mm``, ``rays``, …).
    """

    points: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    data: dict = field(default_factory=dict)
    view_direction: np.ndarray | None = None  # unit, from the cameras towards the subject

    def __len__(self):
        return len(self.points)


def viewing_frame(cameras) -> np.ndarray:
    """World→view rotation: z the cameras' mean optical axis, x along the arm."""
    z = np.mean([c.R[2] for c in cameras], axis=0)
    z /= np.linalg.norm(z)
    x = cameras[-1].C - cameras[0].C if len(cameras) > 1 else cameras[0].R[0]
    x = x - z * (x @ z)
    if np.linalg.norm(x) < 1e-9:
        x = cameras[0].R[0] - z * (cameras[0].R[0] @ z)
    x /= np.linalg.norm(x)
    return np.vstack([x, np.cross(z, x), z])


def triangulate(points: np.ndarray, view_R: np.ndarray, eye: np.ndarray, max_edge_mm: float | None = None,
                max_slope_deg: float = 80.0) -> np.ndarray:
    """TIN faces (F, 3) of ``points`` seen from ``eye`` along ``view_R[2]``.

    ``max_edge_mm`` default: four times the median edge length.
    """
    if len(points) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    v = (points - eye) @ view_R.T
    uv = v[:, :2] / v[:, 2:3]
    tri = Delaunay(uv).simplices
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    edges = np.stack([np.linalg.norm(a - b, axis=1), np.linalg.norm(b - c, axis=1), np.linalg.norm(c - a, axis=1)], 1)
    if max_edge_mm is None:
        max_edge_mm = 4.0 * float(np.median(edges))
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    sight = (a + b + c) / 3 - eye
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    cos = np.abs(np.sum(n * sight, axis=1))
    keep = (edges.max(axis=1) <= max_edge_mm) & (cos >= np.cos(np.radians(max_slope_deg)))
    return tri[keep].astype(np.int64)


def flank_faces(points: np.ndarray, faces: np.ndarray, cameras, max_slope_deg: float = 80.0) -> np.ndarray:
    """Patches (F, 3) over the points that the arm's TIN ``faces`` leaves out, from the end cameras' views.

    Where the skin turns more than ``max_slope_deg`` away from the arm's mean
    view (the torso's flanks), the arm's TIN has no patch, though the arm's
    end cameras still see the skin obliquely. Triangulated again from the
    first and the last camera's view (with the points near them, so that they
    join the skin they continue; long and steep edges removed alike), such
    points belong to the surface again. Each returned patch holds at least
    one of the left-out points.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0 or len(cameras) < 2:
        return np.zeros((0, 3), dtype=np.int64)
    a, b, c = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
    edge = float(np.median(np.concatenate([np.linalg.norm(a - b, axis=1), np.linalg.norm(b - c, axis=1)])))
    max_edge_mm = 4.0 * edge
    used = np.zeros(len(points), bool)
    used[faces.ravel()] = True
    tree = None
    out = []
    for cam in (cameras[0], cameras[-1]):
        lonely = np.nonzero(~used)[0]
        if len(lonely) == 0:
            break
        if tree is None:
            tree = cKDTree(points)
        near = tree.query_ball_point(points[lonely], r=max_edge_mm, return_sorted=False)
        sub = np.unique(np.concatenate([lonely, *[np.asarray(n, dtype=np.int64) for n in near]]))
        f = sub[triangulate(points[sub], cam.R, cam.C, max_edge_mm, max_slope_deg)]
        f = f[~used[f].all(axis=1)]
        used[f.ravel()] = True
        out.append(f)
    return np.concatenate(out) if out else np.zeros((0, 3), dtype=np.int64)


def vertex_normals(points: np.ndarray, faces: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, each turned to face the point ``towards`` (mm)."""
    n = np.zeros_like(points, dtype=float)
    if len(faces):
        a, b, c = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
        fn = np.cross(b - a, c - a)
        for k in range(3):
            np.add.at(n, faces[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.maximum(length, 1e-12), 0.0)
    lonely = length[:, 0] == 0
    if lonely.any() and len(points) >= 3:
        # points in no patch: the normal of the plane through their nearest neighbours
        from scipy.spatial import cKDTree

        k = min(8, len(points))
        _, nb = cKDTree(points).query(points[lonely], k=k)
        q = points[nb] - points[nb].mean(axis=1, keepdims=True)
        _, _, vt = np.linalg.svd(q, full_matrices=False)
        n[lonely] = vt[:, -1]
    flip = np.sum(n * (np.asarray(towards) - points), axis=1) < 0
    n[flip] *= -1
    return n


def off_surface(points: np.ndarray, k: int = 12, factor: float = 6.0, floor_mm: float = 0.3,
                isolation: float = 8.0) -> dict:
    """Points far off the plane through their ``k`` nearest neighbours.

    A point intersected from two rays has no redundancy: a wrong match there
    shows only as a point off the local surface. The limit is ``factor``
    times the robust spread of all points' distances to their neighbourhood
    planes, and at least ``floor_mm``. Points whose ``k``-th neighbour is
    ``isolation`` times farther than usual are off too.

    Returns ``{"off": (N,) bool, "limits": (plane distance mm, k-th
    neighbour distance mm), "neighbours": (N, k) indices}``; the limits and
    neighbours are what :func:`off_surface_again` needs.
    """
    n = len(points)
    if n <= k:
        return {"off": np.zeros(n, bool), "limits": (np.inf, np.inf), "neighbours": np.zeros((n, 0), np.int64)}
    plane, kth, nb = _neighbourhood(points, np.arange(n), k)
    limits = (max(floor_mm, factor * 1.4826 * float(np.median(plane))), isolation * float(np.median(kth)))
    # a point far from every other (a wrong match floating off the skin) has no plane to be tested against
    return {"off": (plane > limits[0]) | (kth > limits[1]), "limits": limits, "neighbours": nb}


def off_surface_again(points: np.ndarray, test: np.ndarray, limits: tuple, k: int = 12) -> np.ndarray:
    """Points of ``test`` (indices into ``points``) off the plane through their ``k`` nearest neighbours, or
    isolated, by an earlier call's ``limits`` (see :func:`off_surface`); a bool mask over ``test``.

    After points were dropped, a point whose neighbours were wrong matches too
    (dropped now) is tested against the skin around it.
    """
    test = np.asarray(test, dtype=np.int64)
    if len(points) <= k or len(test) == 0:
        return np.zeros(len(test), bool)
    plane, kth, _ = _neighbourhood(points, test, k)
    return (plane > limits[0]) | (kth > limits[1])


def _neighbourhood(points, which, k):
    """For the points ``which`` (indices): distance (mm) to the plane through their ``k`` nearest other points,
    distance (mm) to the k-th of them, and their indices (len(which), k)."""
    from scipy.spatial import cKDTree

    dist, nb = cKDTree(points).query(points[which], k=k + 1)
    q = points[nb[:, 1:]]
    centre = q.mean(axis=1)
    _, _, vt = np.linalg.svd(q - centre[:, None], full_matrices=False)
    plane = np.abs(np.sum((points[which] - centre) * vt[:, -1], axis=1))
    return plane, dist[:, -1], nb[:, 1:]


def tangent_bases(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors ``(u, v)`` (N, 3) spanning each point's tangent plane: ``u, v, normal`` right-handed."""
    n = np.asarray(normals, dtype=float)
    other = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    u = np.cross(n, other)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(n, u)


def nearest_points(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Each point's ``k`` nearest points, itself first: ``(distances (N, k) mm, indices (N, k))``."""
    from scipy.spatial import cKDTree

    P = np.asarray(points, dtype=float)
    return cKDTree(P).query(P, k=min(k, len(P)))


def local_quadrics(points: np.ndarray, normals: np.ndarray, weights: np.ndarray | None = None, k: int = 40,
                   scale_mm: float | None = None, chunk: int = 20_000, neighbours: tuple | None = None) -> np.ndarray:
    """The height ``z = c0 + c1 x + c2 y + c3 x² + c4 xy + c5 y²`` (mm) of the skin around every point, fitted by
    weighted least squares to its ``k`` nearest points (itself included) in its tangent frame: ``x, y`` along
    :func:`tangent_bases`' ``u, v``, ``z`` along the point's normal, the point at the origin.

    Each neighbour weighs ``weights`` (e.g. 1 / sigma², default 1) times a Gaussian of its distance of scale
    ``scale_mm`` (default: the median distance of the k-th neighbour); one Tukey reweighting then leaves out a neighbour
    far off the others' quadric (a wrong match nearby). ``c0`` is how far the fitted skin lies from the point
    along its normal; ``c3 + c5`` is the mean curvature (1/mm; negative where the skin bulges towards the
    normal). ``neighbours``: :func:`nearest_points`' result for these points and ``k``, when the caller has it.
    Returns (N, 6); zeros where fewer than 6 points exist. Inputs are not modified.
    """
    P = np.asarray(points, dtype=float)
    N = len(P)
    out = np.zeros((N, 6))
    if N < 6:
        return out
    k = min(k, N)
    w_point = np.ones(N) if weights is None else np.asarray(weights, dtype=float)
    u, v = tangent_bases(normals)
    n = np.asarray(normals, dtype=float)
    dist, nb = nearest_points(P, k) if neighbours is None else neighbours
    h = max(float(np.median(dist[:, -1])) if scale_mm is None else float(scale_mm), 1e-9)
    for lo in range(0, N, chunk):
        sl = slice(lo, min(lo + chunk, N))
        D = P[nb[sl]] - P[sl, None, :]
        # x, y scaled by h so that the normal equations are well scaled; the coefficients are scaled back below
        x = np.einsum("nkj,nj->nk", D, u[sl]) / h
        y = np.einsum("nkj,nj->nk", D, v[sl]) / h
        z = np.einsum("nkj,nj->nk", D, n[sl])
        A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)
        w = np.exp(-(dist[sl] / h) ** 2) * w_point[nb[sl]]
        c = _weighted_fit(A, z, w)
        r = z - np.einsum("nki,ni->nk", A, c)
        scale = 1.4826 * np.median(np.abs(r), axis=1, keepdims=True)
        t = r / np.maximum(4.685 * scale, 1e-12)
        c = _weighted_fit(A, z, w * np.where(np.abs(t) < 1, (1 - t * t) ** 2, 0.0))
        out[sl] = c / np.array([1.0, h, h, h * h, h * h, h * h])
    return out


def _weighted_fit(A, z, w):
    """Batched weighted least squares: ``argmin_c sum_k w_k (A_k c - z_k)²`` for every row; a small ridge keeps a
    neighbourhood along a line (a strip of skin) solvable."""
    AtW = A * w[..., None]
    M = np.einsum("nki,nkj->nij", AtW, A)
    M += (1e-6 * np.trace(M, axis1=1, axis2=2) + 1e-12)[:, None, None] * np.eye(A.shape[-1])
    return np.linalg.solve(M, np.einsum("nki,nk->ni", AtW, z)[..., None])[..., 0]


def window_curvature_bias(quadrics: np.ndarray, points: np.ndarray, cameras, window_px) -> np.ndarray:
    """How far (mm, along each point's normal) area-based matching places a point off curved skin.

    A correlation or least-squares window matches the skin's mean height over the skin it covers, not its
    height at the centre: with the skin ``z = c3 x² + c4 xy + c5 y²`` about the point, a square window of
    ``window_px`` pixels (a number, or one per point) covering ``g`` mm per pixel measures ``(c3 + c5) · s²`` with
    ``s² = window_px² / 12 · g²`` (a uniform window's second moment), i.e. points lie inside skin that bulges towards the cameras and
    outside a hollow. ``g`` is the point's distance to the cameras' mean centre over their mean principal
    distance (px). Cheaper rigs see more skin per pixel: 1000 x 667 px, about 1 mm per pixel, a 9 px window
    and the trunk's 50-200 mm radii put the points 0.03-0.15 mm inside the skin (seed 41, arm A, true
    calibration: -0.065 mm on average, -0.17 mm where the skin is most curved; the points' signed distance to the
    true skin fitted -0.019 + 6.0 (c3 + c5) mm where the 9 px window predicts 6.5 (c3 + c5) mm).
    """
    g = skin_per_pixel(points, cameras)[0]
    return (quadrics[:, 3] + quadrics[:, 5]) * (window_px ** 2 / 12.0) * g ** 2


def skin_per_pixel(points: np.ndarray, cameras) -> tuple[np.ndarray, np.ndarray]:
    """Each point's mm of skin per pixel ``g`` (N,: its distance to the cameras' mean centre over their mean
    principal distance in px) and its unit direction to that centre (N, 3; world frame)."""
    eye = np.mean([c.C for c in cameras], axis=0)
    f = float(np.mean([0.5 * (c.fx + c.fy) for c in cameras]))
    to = eye - np.asarray(points, dtype=float)
    dist = np.linalg.norm(to, axis=1)
    return dist / f, to / np.maximum(dist, 1e-9)[:, None]


def window_obliquity_bias(points: np.ndarray, normals: np.ndarray, cameras, coefficient: float,
                          cap_deg: float = 75.0) -> np.ndarray:
    """How far (mm, along each point's normal; negative: inside the skin) matching places a point that the
    cameras see obliquely, beyond its curvature's bias (:func:`window_curvature_bias`).

    ``coefficient · g² · (1 / cos(theta) - 1)``: ``theta`` the angle between the point's normal and its direction
    to the cameras' mean centre (capped at ``cap_deg``), ``g`` its mm of skin per pixel (distance over the mean
    principal distance), ``coefficient`` in 1/mm. The window's footprint on the skin stretches by ``1 / cos(theta)``
    along the skin's tilt, and what it spans of the skin's shape grows with the footprint's area, as the
    curvature's bias does (``g²``); frontal skin carries none of it. ``coefficient`` is measured, not derived: see
    ``ReconstructionConfig.obliquity_bias``.
    """
    g, to_eye = skin_per_pixel(points, cameras)
    cos_theta = np.sum(np.asarray(normals, dtype=float) * to_eye, axis=1)
    excess = 1.0 / np.maximum(cos_theta, np.cos(np.radians(cap_deg))) - 1.0
    return -coefficient * g ** 2 * excess


def small_components(n_points: int, faces: np.ndarray, min_points: int) -> np.ndarray:
    """Points (bool mask) in patches of the TIN that hold fewer than ``min_points`` points.

    Wrong matches that agree with each other form small islands, cut off from
    the skin once long and steep edges are removed; points in no patch at all
    count as islands of one.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if n_points == 0:
        return np.zeros(0, bool)
    f = np.asarray(faces, dtype=np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_points, n_points))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    return size[label] < min_points


def subset(surface: PointSurface, keep: np.ndarray) -> PointSurface:
    """The points where ``keep`` is true, with the patches whose three vertices are all kept."""
    keep = np.asarray(keep, dtype=bool)
    new_index = np.cumsum(keep) - 1
    faces = surface.faces[keep[surface.faces].all(axis=1)]
    return PointSurface(surface.points[keep], surface.normals[keep], new_index[faces],
                        {k: np.asarray(v)[keep] for k, v in surface.data.items()}, surface.view_direction)


def in_patches(surface: PointSurface) -> PointSurface:
    """The surface without its points in no patch (the flanks' points, see :func:`flank_faces`).

    Registration pairs a surface's points with its neighbour's patches; a point
    the arm's TIN leaves out was seen only obliquely by the arm's cameras and
    is left out of the registration too (not of the fused torso).
    """
    keep = np.zeros(len(surface.points), bool)
    keep[np.asarray(surface.faces, dtype=np.int64).ravel()] = True
    return surface if keep.all() else subset(surface, keep)


def make_surface(points, cameras, data=None, max_edge_mm=None, max_slope_deg=80.0) -> PointSurface:
    """The TIN surface of an arm's points seen by ``cameras``."""
    points = np.asarray(points, dtype=float)
    R = viewing_frame(cameras)
    eye = np.mean([c.C for c in cameras], axis=0)
    faces = triangulate(points, R, eye, max_edge_mm, max_slope_deg)
    normals = vertex_normals(points, faces, eye)
    return PointSurface(points, normals, faces, dict(data or {}), R[2])


_PLY_TYPES = {np.dtype("float32"): "float", np.dtype("float64"): "double", np.dtype("int32"): "int",
              np.dtype("uint8"): "uchar", np.dtype("int64"): "int", np.dtype("uint32"): "uint",
              np.dtype("uint16"): "ushort", np.dtype("int16"): "short"}


def write_ply(path, points, normals=None, faces=None, data: dict | None = None, comments=()) -> None:
    """Binary little-endian PLY: x y z [nx ny nz] [per-point scalars] [faces]; written atomically."""
    path = Path(path)
    points = np.asarray(points, dtype=np.float64)
    cols = [("x", points[:, 0]), ("y", points[:, 1]), ("z", points[:, 2])]
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float32)
        cols += [("nx", normals[:, 0]), ("ny", normals[:, 1]), ("nz", normals[:, 2])]
    for name, values in (data or {}).items():
        values = np.asarray(values)
        if values.shape != (len(points),):
            raise ValueError(f"PLY property {name!r} has shape {values.shape}, expected ({len(points)},)")
        if values.dtype == np.int64:
            values = values.astype(np.int32)
        cols.append((name, values))
    dtype = np.dtype([(n, v.dtype if v.dtype in _PLY_TYPES else np.float64) for n, v in cols]).newbyteorder("<")
    rec = np.empty(len(points), dtype=dtype)
    for n, v in cols:
        rec[n] = v
    header = ["ply", "format binary_little_endian 1.0", *[f"comment {c}" for c in comments],
              f"element vertex {len(points)}"]
    header += [f"property {_PLY_TYPES[dtype[n].newbyteorder('=')]} {n}" for n in dtype.names]
    f = np.zeros((0, 3), np.int32) if faces is None else np.asarray(faces, dtype=np.int32)
    if faces is not None:
        header += [f"element face {len(f)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
        if faces is not None:
            frec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
            frec["n"] = 3
            frec["i"] = f
            fh.write(frec.tobytes())
    tmp.replace(path)


def read_ply(path) -> dict:
    """Vertices (``points``, ``normals`` when present, other scalars), faces and header comments of a PLY file.

    Binary little-endian and ASCII files with triangle faces.
    """
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", "replace").splitlines()
    fmt, elements, current, comments = None, [], None, []
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "comment":
            comments.append(line.strip()[len("comment"):].strip())
        elif parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            current = {"name": parts[1], "count": int(parts[2]), "props": []}
            elements.append(current)
        elif parts[0] == "property" and current is not None:
            current["props"].append(parts[1:])
    types = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "int": "<i4", "int32": "<i4",
             "uint": "<u4", "uint32": "<u4", "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
             "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2"}
    out = {}
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        for el in elements:
            if el["name"] == "vertex":
                n = len(el["props"])
                vals = np.array(tokens[pos:pos + n * el["count"]], dtype=float).reshape(el["count"], n)
                pos += n * el["count"]
                out["vertex"] = {p[-1]: vals[:, i] for i, p in enumerate(el["props"])}
            elif el["name"] == "face":
                faces = []
                for _ in range(el["count"]):
                    k = int(tokens[pos])
                    faces.append([int(t) for t in tokens[pos + 1:pos + 1 + k]])
                    pos += 1 + k
                out["faces"] = np.array([f[:3] for f in faces], dtype=np.int64).reshape(-1, 3)
    elif fmt == "binary_little_endian":
        pos = body_start
        for el in elements:
            if el["name"] == "vertex":
                dt = np.dtype([(p[-1], types[p[0]]) for p in el["props"]])
                rec = np.frombuffer(raw, dtype=dt, count=el["count"], offset=pos)
                pos += dt.itemsize * el["count"]
                out["vertex"] = {n: rec[n].astype(float) for n in dt.names}
            elif el["name"] == "face":
                p = el["props"][0]
                if p[0] != "list":
                    raise ValueError(f"{path}: face element without a vertex list")
                ct, it = types[p[1]], types[p[2]]
                dt = np.dtype([("n", ct), ("i", it, (3,))])
                rec = np.frombuffer(raw, dtype=dt, count=el["count"], offset=pos)
                if el["count"] and np.any(rec["n"] != 3):
                    raise ValueError(f"{path}: only triangle faces are supported")
                pos += dt.itemsize * el["count"]
                out["faces"] = rec["i"].astype(np.int64)
            else:
                raise ValueError(f"{path}: unsupported element {el['name']!r} before the data end")
    else:
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    v = out.get("vertex")
    if v is None or not {"x", "y", "z"} <= set(v):
        raise ValueError(f"{path}: no vertex positions")
    res = {"points": np.column_stack([v["x"], v["y"], v["z"]]), "faces": out.get("faces", np.zeros((0, 3), np.int64))}
    if {"nx", "ny", "nz"} <= set(v):
        res["normals"] = np.column_stack([v["nx"], v["ny"], v["nz"]])
    res["data"] = {k: a for k, a in v.items() if k not in ("x", "y", "z", "nx", "ny", "nz")}
    res["comments"] = comments
    return res
