"""ICPatch: point-to-patch registration of overlapping surfaces (Habib et al. 2001; Habib and Cheng 2006).

The points of one surface are registered to the triangular patches of
another by a 3D similarity transformation (scale, three rotations, three
translations). The observation is the coplanarity condition: a transformed
point and the three vertices of its patch enclose zero volume, i.e. the
point's normal distance to the patch plane is zero. Each point's patch is the
closest one whose interior the point projects into; pairs farther apart than
an acceptance distance, tightened as the solution converges, or whose
normals disagree, are not used, which keeps points over the other
surface's holes and edges out of the adjustment.

Frames: ``T(x) = s·R·x + t`` maps the moving surface's frame into the fixed
one's (mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .bundle import rodrigues
from .surface import PointSurface


@dataclass(frozen=True)
class ICPatchConfig:
    initial_distance_mm: float = 25.0  # acceptance distance at the start (arms swing a few mm and ~1 deg)
    min_distance_mm: float = 0.5  # it never tightens below this
    tighten_k: float = 4.0  # acceptance distance: k times the RMS normal distance of the last iteration
    max_normal_angle_deg: float = 30.0  # point and patch normals further apart are not a pair
    edge_margin: float = 0.02  # barycentric margin: closest points on a patch's edge are outside it
    max_iterations: int = 60
    # corrections below these are converged: far below their standard deviations; the set of
    # pairs still changes by a few points per iteration, so smaller ones jitter rather than vanish
    tol_rotation_rad: float = 1e-6
    tol_translation_mm: float = 1e-3
    tol_scale: float = 1e-5
    estimate_scale: bool = True


@dataclass
class Transform:
    """A 3D similarity: ``x' = scale · R @ x + t`` (mm)."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    @classmethod
    def identity(cls):
        return cls(1.0, np.eye(3), np.zeros(3))

    def apply(self, x):
        return self.scale * np.asarray(x) @ self.R.T + self.t

    def rotate(self, n):
        return np.asarray(n) @ self.R.T

    def inverse(self):
        Ri = self.R.T
        return Transform(1.0 / self.scale, Ri, -Ri @ self.t / self.scale)

    def compose(self, other):
        """``self ∘ other``: first ``other``, then ``self``."""
        return Transform(self.scale * other.scale, self.R @ other.R, self.scale * self.R @ other.t + self.t)

    def to_dict(self):
        return {"scale": float(self.scale), "R": self.R.tolist(), "t": self.t.tolist()}


class PatchIndex:
    """Closest-patch queries on a fixed surface (Open3D raycasting scene)."""

    def __init__(self, surface: PointSurface):
        if len(surface.faces) == 0:
            raise ValueError("the surface has no patches to register against")
        self.surface = surface
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(surface.points.astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(surface.faces.astype(np.int32))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)
        P = surface.points
        F = surface.faces
        n = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        # patch normals turned like the vertex normals (towards the viewer)
        vn = surface.normals[F].sum(axis=1)
        n[np.sum(n * vn, axis=1) < 0] *= -1
        self.normals = n
        self.anchor = P[F[:, 0]]

    def closest(self, x: np.ndarray, margin: float):
        """Patch id (N,), whether ``x`` projects into its interior (N,), patch normal (N, 3), a vertex (N, 3)."""
        ans = self.scene.compute_closest_points(o3d.core.Tensor(np.asarray(x, np.float32)))
        pid = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy()
        w = np.column_stack([1 - uv[:, 0] - uv[:, 1], uv])
        inside = (w > margin).all(axis=1) & (pid >= 0)
        pid = np.clip(pid, 0, len(self.normals) - 1)
        return pid, inside, self.normals[pid], self.anchor[pid]


def correspondences(points, normals, index: PatchIndex, transform: Transform, max_distance: float,
                    cfg: ICPatchConfig):
    """Accepted point–patch pairs under ``transform``: (point ids, patch normal, patch vertex, normal distance)."""
    x = transform.apply(points)
    pid, inside, n, p0 = index.closest(x, cfg.edge_margin)
    d = np.sum((x - p0) * n, axis=1)
    ok = inside & (np.abs(d) <= max_distance)
    if normals is not None:
        cosang = np.sum(transform.rotate(normals) * n, axis=1)
        ok &= cosang >= np.cos(np.radians(cfg.max_normal_angle_deg))
    idx = np.nonzero(ok)[0]
    return idx, n[idx], p0[idx], d[idx]


def icpatch(moving: PointSurface, fixed: PointSurface, initial: Transform | None = None,
            cfg: ICPatchConfig | None = None, index: PatchIndex | None = None) -> dict:
    """Register the points of ``moving`` to the patches of ``fixed``.

    Returns ``{"transform", "sigmas" (scale, omega, phi, kappa [rad], tx, ty, tz [mm]),
    "average_normal_distance_mm", "rms_normal_distance_mm", "matched_fraction", "pairs", "iterations",
    "converged"}``.
    """
    cfg = cfg or ICPatchConfig()
    T = initial or Transform.identity()
    index = index or PatchIndex(fixed)
    X = moving.points
    centre = X.mean(axis=0)
    dist = cfg.initial_distance_mm
    converged = False
    it = 0
    for it in range(1, cfg.max_iterations + 1):
        idx, n, p0, d = correspondences(X, moving.normals, index, T, dist, cfg)
        if len(idx) < 7:
            raise ValueError(f"ICPatch: only {len(idx)} point-patch pairs within {dist:.1f} mm: "
                             "the surfaces do not overlap under the initial transformation")
        # increments about the moving surface's centre: x' = (1+ds)(I+[w]x)(Y) + t + dt, Y = T(x) - T(c)
        Y = T.apply(X[idx]) - T.apply(centre)
        J = np.column_stack([np.sum(n * Y, axis=1), np.cross(Y, n), n])
        if not cfg.estimate_scale:
            J = np.column_stack([np.zeros(len(idx)), J[:, 1:]])
        N = J.T @ J + np.diag([0 if cfg.estimate_scale else 1.0, 0, 0, 0, 0, 0, 0])
        dx = np.linalg.solve(N, -J.T @ d)
        ds, w, dt = dx[0], dx[1:4], dx[4:]
        dR = rodrigues(w)
        c_moved = T.apply(centre)
        # apply: new T(x) = (1+ds) dR (T(x) - c_moved) + c_moved + dt
        T = Transform(T.scale * (1 + ds), dR @ T.R, (1 + ds) * dR @ (T.t - c_moved) + c_moved + dt)
        rms = float(np.sqrt(np.mean(d ** 2)))
        dist = max(cfg.min_distance_mm, min(dist, cfg.tighten_k * rms))
        if np.linalg.norm(w) < cfg.tol_rotation_rad and np.linalg.norm(dt) < cfg.tol_translation_mm \
                and abs(ds) < cfg.tol_scale:
            converged = True
            break
    idx, n, p0, d = correspondences(X, moving.normals, index, T, dist, cfg)
    Y = T.apply(X[idx]) - T.apply(centre)
    J = np.column_stack([np.sum(n * Y, axis=1), np.cross(Y, n), n])
    dof = max(len(idx) - (7 if cfg.estimate_scale else 6), 1)
    s0 = float(np.sqrt(np.sum(d ** 2) / dof))
    if not cfg.estimate_scale:
        J = J[:, 1:]
    cov = s0 ** 2 * np.linalg.inv(J.T @ J)
    sig = np.sqrt(np.diag(cov))
    if not cfg.estimate_scale:
        sig = np.concatenate([[0.0], sig])
    return {"transform": T, "sigmas": {k: float(v) for k, v in zip(
                ("scale", "omega_rad", "phi_rad", "kappa_rad", "tx_mm", "ty_mm", "tz_mm"), sig)},
            "average_normal_distance_mm": float(np.mean(np.abs(d))),
            "rms_normal_distance_mm": float(np.sqrt(np.mean(d ** 2))),
            "matched_fraction": float(len(idx) / len(X)), "pairs": int(len(idx)),
            "acceptance_distance_mm": float(dist), "iterations": it, "converged": converged}
