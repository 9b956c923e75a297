"""Torso point clouds: reading, thinning, outward normals, local planes.

A torso is a set of points (mm) in the rig frame (the reference arm's
calibration frame, +Z up as the test field stands) with unit normals that
point out of the body. Faces are not needed: every stage works on points and
their local planes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .config import SurfaceConfig


@dataclass
class Torso:
    """Points (N, 3) mm and outward unit normals (N, 3), rig frame; ``data``: per-point arrays."""

    points: np.ndarray
    normals: np.ndarray
    data: dict = field(default_factory=dict)
    source: str = ""
    # what the file says of the patient: {"posterior": [x, y, z], "back_towards": [...], "source": "rig"}
    # from the rig's footplate (the reconstruction's PLY comment); None when unknown
    patient: dict | None = None

    def __len__(self):
        return len(self.points)

    def transformed(self, R: np.ndarray, t: np.ndarray) -> "Torso":
        """The torso moved by ``x' = R x + t``."""
        patient = None
        if self.patient is not None:
            patient = {**self.patient, "posterior": (np.asarray(self.patient["posterior"], float) @ R.T).tolist()}
        return Torso(self.points @ R.T + t, self.normals @ R.T, dict(self.data), self.source, patient)


class TorsoError(ValueError):
    """A torso file that cannot be analysed; the message names the file and the problem."""


def read_torso(path, cfg: SurfaceConfig | None = None) -> Torso:
    """A torso PLY (binary or ASCII; ``torsoscan reconstruct``'s ``torso.ply``), normals made outward.

    Raises :class:`TorsoError` naming the file for a missing file, a file that
    is not a PLY, or one with too few points.
    """
    from recon_engine.surface import read_ply

    cfg = cfg or SurfaceConfig()
    path = Path(path)
    if not path.exists():
        raise TorsoError(f"{path}: no such file")
    if path.is_dir():
        raise TorsoError(f"{path}: is a folder, expected a torso PLY file")
    try:
        ply = read_ply(path)
    except (ValueError, KeyError, IndexError, UnicodeDecodeError) as exc:
        msg = str(exc)
        raise TorsoError(msg if msg.startswith(str(path)) else f"{path}: not a readable PLY file ({msg})") from None
    pts = ply["points"]
    good = np.isfinite(pts).all(axis=1)
    if good.sum() < 500:
        raise TorsoError(f"{path}: only {int(good.sum())} valid points, a torso needs at least 500")
    normals = ply.get("normals")
    data = {k: np.asarray(v)[good] for k, v in ply.get("data", {}).items()}
    torso = make_torso(pts[good], None if normals is None else normals[good], data, cfg, source=str(path))
    from recon_engine.results import parse_posterior_comment

    torso.patient = parse_posterior_comment(ply.get("comments", ()))
    return torso


def make_torso(points, normals=None, data=None, cfg: SurfaceConfig | None = None, source: str = "") -> Torso:
    """A :class:`Torso` from points (and normals if known), thinned to ``cfg.max_points``, normals outward."""
    cfg = cfg or SurfaceConfig()
    points = np.asarray(points, dtype=float)
    data = dict(data or {})
    if len(points) > cfg.max_points:
        keep = np.sort(np.random.default_rng(cfg.seed).choice(len(points), cfg.max_points, replace=False))
        points = points[keep]
        normals = None if normals is None else np.asarray(normals)[keep]
        data = {k: np.asarray(v)[keep] for k, v in data.items()}
    if normals is None or not np.isfinite(normals).all():
        normals = orient_consistently(points, estimate_normals(points, cfg.normal_neighbours), cfg.normal_neighbours)
    else:
        # given normals (the reconstruction's point towards the cameras, i.e. out of the body) are kept as they are:
        # a geometric rule fails on arms and between the legs, whose skin faces the trunk
        normals = np.asarray(normals, dtype=float)
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return Torso(points, normals, data, source)


def orient_consistently(points: np.ndarray, normals: np.ndarray, k: int = 12) -> np.ndarray:
    """Estimated normals turned consistently over the surface (Open3D's tangent-plane propagation), outward overall.

    Falls back to :func:`orient_outward` (away from the trunk's vertical axis) if the propagation fails.
    """
    try:
        from recon_engine.o3d import o3d

        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pc.normals = o3d.utility.Vector3dVector(orient_outward(points, normals))
        pc.orient_normals_consistent_tangent_plane(k)
        n = np.asarray(pc.normals).copy()
    except Exception:  # noqa: BLE001 - Open3D raises RuntimeError and others; the rule below still works
        return orient_outward(points, normals)
    # the whole surface one way or the other: outward where most points say so
    axis = axis_points(points, points[:, 2])
    radial = np.sum(n[:, :2] * (points[:, :2] - axis), axis=1)
    return -n if np.median(np.sign(radial)) < 0 else n


def estimate_normals(points: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit normals (N, 3) of the planes through each point's ``k`` nearest neighbours (unoriented)."""
    k = min(k, len(points))
    _, nb = cKDTree(points).query(points, k=k)
    q = points[nb] - points[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", q, q)
    _, vec = np.linalg.eigh(cov)
    return vec[:, :, 0]


def axis_points(points: np.ndarray, z: np.ndarray, bin_mm: float = 20.0) -> np.ndarray:
    """The trunk's vertical axis at heights ``z``: the median X, Y of the points in each horizontal band."""
    lo, hi = points[:, 2].min(), points[:, 2].max()
    edges = np.arange(lo, hi + bin_mm, bin_mm)
    idx = np.clip(np.digitize(points[:, 2], edges) - 1, 0, len(edges) - 1)
    centres, xy = [], []
    for b in np.unique(idx):
        sel = points[idx == b]
        if len(sel) >= 10:
            centres.append(sel[:, 2].mean())
            xy.append(np.median(sel[:, :2], axis=0))
    centres, xy = np.asarray(centres), np.asarray(xy)
    if len(centres) == 0:
        return np.tile(np.median(points[:, :2], axis=0), (len(z), 1))
    return np.column_stack([np.interp(z, centres, xy[:, 0]), np.interp(z, centres, xy[:, 1])])


def orient_outward(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Normals turned to point away from the trunk's vertical axis (horizontally outward).

    Near-horizontal skin (shoulder tops) is oriented by the vertical instead:
    up above the trunk's mid height, down below it.
    """
    axis = axis_points(points, points[:, 2])
    radial = points[:, :2] - axis
    s = np.sum(normals[:, :2] * radial, axis=1)
    flat = np.abs(normals[:, 2]) > 0.9
    mid = np.median(points[:, 2])
    s = np.where(flat, normals[:, 2] * np.sign(points[:, 2] - mid + 1e-9), s)
    n = normals.copy()
    n[s < 0] *= -1
    return n


def spacings(points: np.ndarray, k: int = 16, sample: int = 5000, seed: int = 0) -> tuple[float, float]:
    """The nearest-neighbour spacing and the sampling spacing (mm), from one neighbour query of a sample.

    The nearest-neighbour spacing is the median distance to the nearest
    point. The sampling spacing is the side of the area each point holds,
    ``sqrt(pi r_k^2 / k)`` with ``r_k`` the median distance to the k-th
    nearest neighbour: it sees clustered samples (matched features bunch on
    the pattern's blobs, with gaps between) as sparse as they are, so a grid
    of cells this size is mostly filled.
    """
    rng = np.random.default_rng(seed)
    k = max(1, min(k, len(points) - 1))
    idx = rng.choice(len(points), min(sample, len(points)), replace=False)
    d, _ = cKDTree(points).query(points[idx], k=k + 1)
    return float(np.median(d[:, 1])), float(np.sqrt(np.pi * np.median(d[:, k]) ** 2 / k))


def point_spacing(points: np.ndarray, sample: int = 5000, seed: int = 0) -> float:
    """Median distance (mm) from a point to its nearest neighbour."""
    return spacings(points, 1, sample, seed)[0]


def sampling_spacing(points: np.ndarray, k: int = 16, sample: int = 5000, seed: int = 0) -> float:
    """The surface's sampling spacing (mm): the side of the area each point holds (see :func:`spacings`)."""
    return spacings(points, k, sample, seed)[1]


class PlaneIndex:
    """Signed normal distances to a fixed torso through the mean planes of its nearest points."""

    def __init__(self, torso: Torso, k: int = 6):
        self.torso = torso
        self.tree = cKDTree(torso.points)
        self.k = max(1, min(k, len(torso)))
        self.spacing = point_spacing(torso.points)

    def distances(self, x: np.ndarray, max_tangential: float = 3.0):
        """For points ``x`` (M, 3): signed distance (mm, + outside), plane normal (M, 3), plane point (M, 3), over-surface mask.

        A point whose foot lies farther than ``max_tangential`` point spacings
        from the nearest surface point is over a hole or beyond the edge.
        """
        d, nb = self.tree.query(x, k=self.k, workers=-1)
        if self.k == 1:
            nb = nb[:, None]
        n = self.torso.normals[nb].mean(axis=1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        p = self.torso.points[nb].mean(axis=1)
        r = x - p
        dist = np.sum(r * n, axis=1)
        x0 = x - dist[:, None] * n
        d0, _ = self.tree.query(x0, k=1, workers=-1)
        over = d0 <= max_tangential * self.spacing
        return dist, n, p, over
