"""ICPatch: point-to-patch registration of overlapping surfaces (Habib et al. 2001; Habib and Cheng 2006).

The points of one surface are registered to the triangular patches of
another by a 3D similarity transformation (scale, three rotations, three
translations; by default the scale is held at 1, the calibration's, see
``ICPatchConfig.estimate_scale``). The observation is the coplanarity condition: a transformed
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

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .bundle import rodrigues
from .parallel import cores
from .surface import PointSurface, subset


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
    # each arm's scale is estimated (the 7-parameter similarity of the paper's ICPatch), or held at 1 (rigid). The
    # calibration fixes every arm's scale to the test field's survey (paper scale, our calibration against the
    # truth: the distances between an arm's cameras off by 0.2-3.4e-5 of their length), while a free scale
    # absorbs what is left of the surfaces' shape errors in the narrow overlaps. Paper scale, our calibration,
    # 9 arms of 3 captures (docs/benchmarks.md, ninth session), mean position error: scale free 0.0163 mm,
    # held by a prior of 1e-4 0.0162, of 3e-5 0.0156, rigid 0.0125 (Open3D's multiway 0.0128). Tiny preset, free:
    # arms C and D took scales of 0.9972 and 0.9970 (3 mm at 1 m) and the torso's RMS was 1.06 mm (rigid 0.53)
    estimate_scale: bool = False
    # mm (None: off): point-patch pairs whose point lies this close to its own surface's rim, or whose foot this
    # close to the other surface's rim, are not used in the multiple registration. At the true placement the
    # points within 10 mm of a rim lie 1-11 um below the skin and the other's patches there 2-8 um (visit0-a).
    # 5 mm: displacement error 0.0172 -> 0.0106 mm over 9 arms (docs/benchmarks.md); 10 mm leaves the narrow
    # overlaps too few pairs. The report's Table 1 still measures the fit over the whole overlap
    rim_margin_mm: float | None = 5.0
    # patches with an edge longer than this many median edges are not used (None: all): long patches are chords
    # below the curved skin where an arm sees it obliquely, and their sagitta biases the solution. Paper scale,
    # visit0-a, our calibration, flat patches, displacement errors of B, C, D: all patches 0.0028-0.0054 deg, 0.032-0.055 mm;
    # 2.0: 0.0016-0.0021 deg, 0.026-0.038 mm; 1.75: 0.0016-0.0029 deg, 0.022-0.034 mm; 1.5: 0.0021-0.0032 deg,
    # 0.015-0.032 mm. Weak overlaps keep all patches (min_compact_pairs), and the torso status checks that
    # every arm is held (max_position_sigma_factor), so at the tiny preset no arm slides any more.
    max_patch_edge: float | None = 1.75
    # a pair keeps the compact patches only if they give at least this share of the pairs all patches give
    # and at least min_compact_pairs; otherwise its overlap lies where only long patches are, or it is weak
    # anyway (tiny preset: B-C 26 pairs, 20 compact, which fell below min_pairs in the adjustment and let
    # arms C and D slide 7 mm): holding the arm matters more than the long patches' bias, so it uses all
    min_compact_share: float = 0.5
    min_compact_pairs: int = 100
    # patches curved by their vertices' normals (the TIN's): a flat patch is a chord below the convex skin by its
    # sagitta, all one way (paper scale, visit0-a, points moved onto the true skin: +3 to +6 um at the true
    # placement, and B, C, D misplaced by 0.005-0.010 mm; curved: under 1 um, 0.001-0.002 mm). The residual is
    # the distance to the curved patch along the normal interpolated from the vertices.
    curved_patches: bool = True
    # observe each pair in both directions: the two directions' remaining errors pull the arms oppositely.
    # Measured with curved patches and all points (visit0-a, our calibration, B/C/D position error): one
    # direction 0.013/0.021/0.019 mm, both 0.012/0.018/0.015 mm
    symmetric: bool = True
    # points of each pair's moving surface the multiple registration observes (None: all). A subsample of
    # 20 000 of an arm's ~65 000 points left B/C/D 1.5-2.5x further off on points with 0.03 mm noise; 40 000
    # were as good as all on visit0-a (0.012/0.016/0.012 mm against 0.012/0.018/0.015) in half the time
    max_points_per_pair: int | None = 40000
    # points of the moving arm each pair-wise ICPatch of the chain registers (None: all): the chain only starts
    # the multiple registration, which observes max_points_per_pair. Paper scale, seed 33, our calibration: with
    # 10 000 of ~70 000 the final transforms moved every point by under 0.25 um, and the registration took
    # 5.3 s instead of 7.5 s
    chain_points: int | None = 10000
    freeze_after: int = 12  # iterations with fresh point-patch pairs; then they are kept until convergence
    negligible_sigma: float = 0.01  # corrections below this many of their standard deviations have vanished
    overlap_distance_mm: float = 3.0  # a point over a patch interior this close is in the overlap
    min_pairs: int = 20  # fewer point-patch pairs: the surfaces barely overlap, the result is not trusted
    max_average_distance_mm: float = 0.5  # a pair fitting worse than this (or 3x the points' precision) failed
    # an arm is not held when the adjustment leaves any point of its surface less certain than this many
    # times its points' median precision (1 sigma, weakest direction; see arm_strength). Measured (visit0-a,
    # position sigma / point precision): paper scale 0.17-0.27 (0.012-0.020 mm on 0.07 mm points); tiny
    # preset 0.6-0.7 for B, 3.0-3.7 for the weakly overlapping C and D (their true errors 1.1-1.35 mm on
    # 0.44 mm points), and 15-34 where C and D slid 6.6-76 mm after the weak pair B-C dropped out. 6 lies
    # between, and stays far above what the paper scale needs (limit there ~0.43 mm)
    max_position_sigma_factor: float = 6.0
    threads: int = 0  # the pairs' closest-patch queries run on this many threads; 0: one per core


class TooFewPairs(ValueError):
    """ICPatch found too few point-patch pairs within its acceptance distance to adjust a transformation."""


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

    def __init__(self, surface: PointSurface, max_edge_factor: float | None = None,
                 vertex_normals: np.ndarray | None = None, rim_of: PatchIndex | None = None):
        if len(surface.faces) == 0:
            raise ValueError("the surface has no patches to register against")
        self.full_surface = surface  # the rim is that of all patches (see rim_tree)
        self._rim_of = rim_of  # an index of the same surface whose rim this one shares
        if max_edge_factor is not None:
            # long patches are chords far below the curved skin (where the arm sees it obliquely, the TIN
            # stretches): their sagitta biases the normal distances, so only compact patches are used
            P0, F0 = surface.points, surface.faces
            e = np.stack([np.linalg.norm(P0[F0[:, a]] - P0[F0[:, b]], axis=1) for a, b in ((0, 1), (1, 2), (2, 0))],
                         axis=1).max(axis=1)
            keep = e <= max_edge_factor * float(np.median(e))
            if keep.sum() >= 3:
                surface = PointSurface(surface.points, surface.normals, F0[keep], surface.data)
        self.surface = surface
        from .o3d import o3d  # here, not at the top: a process that only reconstructs arms (a clinic worker's arm
        # task) imports this module but never registers: Open3D need not load there

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
        # unit skin normals at the vertices: with them a patch stands for the curved skin, not its chord
        self.vertex_normals = None if vertex_normals is None else np.asarray(vertex_normals, dtype=float)

    @cached_property
    def rim_tree(self):
        """KD-tree of the TIN's rim vertices (on edges of one patch, all patches counted; None if it has none).
        Built on first use: only the multiple registration's ``rim_margin_mm`` needs it."""
        if self._rim_of is not None:
            return self._rim_of.rim_tree
        F = self.full_surface.faces.astype(np.int64)
        n = len(self.full_surface.points)
        E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        # each edge as one integer: a 1-D unique is far faster than np.unique(axis=0) on rows
        key, count = np.unique(E[:, 0] * n + E[:, 1], return_counts=True)
        once = key[count == 1]
        rim = np.unique(np.concatenate([once // n, once % n]))
        return cKDTree(self.full_surface.points[rim]) if len(rim) else None

    @cached_property
    def vertex_rim_distance(self) -> np.ndarray:
        """Each vertex's distance to the TIN's rim (N,, mm; inf if the TIN has no rim)."""
        if self._rim_of is not None:
            return self._rim_of.vertex_rim_distance
        P = self.full_surface.points
        return self.rim_tree.query(P)[0] if self.rim_tree is not None else np.full(len(P), np.inf)

    def closest(self, x: np.ndarray, margin: float):
        """Patch id (N,), whether ``x`` projects into its interior (N,), patch normal (N, 3), the point of
        the patch under ``x`` (N, 3) and the distance of ``x`` to the surface (N,, mm)."""
        if len(x) == 0:
            z = np.zeros((0, 3))
            return np.zeros(0, np.int64), np.zeros(0, bool), z, z, np.zeros(0)
        from .o3d import o3d  # loaded by __init__ already

        ans = self.scene.compute_closest_points(o3d.core.Tensor(np.asarray(x, np.float32)))
        gap = np.linalg.norm(np.asarray(x, dtype=float) - ans["points"].numpy(), axis=1)
        pid = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy()
        w = np.column_stack([1 - uv[:, 0] - uv[:, 1], uv])
        inside = (w > margin).all(axis=1) & (pid >= 0)
        pid = np.clip(pid, 0, len(self.normals) - 1)
        n, p0 = self.normals[pid], self.anchor[pid]
        if self.vertex_normals is not None:
            # the point of the curved patch under x: a flat patch is a chord below convex skin by its
            # sagitta (a few micrometres on 3 mm patches, all one way), which would bias the registration.
            # Phong's projection onto the vertices' tangent planes, halfway, is exact on a quadric
            # (Boubekeur and Alexa 2008 with shape factor 1/2)
            x = np.asarray(x, dtype=float)
            q = x - np.sum((x - p0) * n, axis=1)[:, None] * n
            F = self.surface.faces[pid]
            P, NV = self.surface.points[F], self.vertex_normals[F]  # (N, 3, 3)
            lift = np.sum((q[:, None, :] - P) * NV, axis=2)  # q's height over each vertex's tangent plane
            p0 = q - 0.5 * np.sum((w * lift)[:, :, None] * NV, axis=1)
            # and the curved patch's normal there (the vertex normals average several patches: less noisy)
            n = np.sum(w[:, :, None] * NV, axis=1)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return pid, inside, n, p0, gap


def patch_indices(surfaces: dict, cfg: ICPatchConfig) -> dict:
    """Per arm ``(all patches, compact patches or None)``: the two patch sets a pair can register against."""
    out = {}
    for a, s in surfaces.items():
        vn = s.normals if cfg.curved_patches else None
        full = PatchIndex(s, None, vn)
        out[a] = (full, PatchIndex(s, cfg.max_patch_edge, vn, rim_of=full) if cfg.max_patch_edge is not None else None)
    return out


def choose_patches(points, normals, indices: tuple, transform: Transform, max_distance: float,
                   cfg: ICPatchConfig) -> tuple:
    """The patch set a pair registers against: the compact patches, unless they leave the overlap weak.

    Long patches are biased chords, but where two arms overlap only at the
    oblique periphery of the fixed one they are all there is: dropping them
    would leave the pair (and an arm it holds) without support. So the compact
    set is used when it gives at least ``min_compact_share`` of the pairs that
    all patches give, and at least ``min_compact_pairs``. Returns ``(index, "compact" or "all")``.
    """
    full, compact = indices
    if compact is None:
        return full, "all"
    n_full = _count_pairs(points, normals, full, transform, max_distance, cfg)
    n_compact = _count_pairs(points, normals, compact, transform, max_distance, cfg)
    if n_compact >= max(cfg.min_pairs, cfg.min_compact_pairs, cfg.min_compact_share * n_full):
        return compact, "compact"
    return full, "all"


def _count_pairs(points, normals, index, transform, max_distance, cfg, sample: int = 8000) -> int:
    """About how many point–patch pairs ``points`` make: counted on every k-th point (a decision, not an
    observation), scaled back."""
    k = max(1, len(points) // sample)
    nrm = None if normals is None else normals[::k]
    return k * len(correspondences(points[::k], nrm, index, transform, max_distance, cfg)[0])


def correspondences(points, normals, index: PatchIndex, transform: Transform, max_distance: float,
                    cfg: ICPatchConfig, near: dict | None = None, rim_distance: np.ndarray | None = None):
    """Accepted point–patch pairs under ``transform``: (point ids, patch normal, point of the patch under the
    point, normal distance (mm)), the last three in the fixed surface's frame.

    ``near`` is an optional dict kept by the caller between calls on the same
    points and patches: points that were far from the surface at a full
    query, and cannot have come within ``max_distance`` since (the
    transformation's largest motion of any point bounds that), are not
    queried again. Most of an arm lies outside its overlap with another.
    """
    x = transform.apply(points)
    sel = np.arange(len(x))
    if near is not None:
        corners = np.array(np.meshgrid(*zip(points.min(axis=0), points.max(axis=0)))).T.reshape(-1, 3)
        moved = (float(np.max(np.linalg.norm(transform.apply(corners) - near["at"].apply(corners), axis=1)))
                 if "gap" in near else np.inf)
        if moved > near.setdefault("slack_mm", 5.0):
            near["gap"], near["at"], moved = None, transform, 0.0  # (re)start: query every point
        else:
            sel = np.nonzero(near["gap"] - moved <= max_distance)[0]
    pid, inside, n, p0, gap = index.closest(x[sel], cfg.edge_margin)
    if near is not None and near["gap"] is None:
        near["gap"] = gap
    d = np.sum((x[sel] - p0) * n, axis=1)
    ok = inside & (np.abs(d) <= max_distance)
    if normals is not None:
        cosang = np.sum(transform.rotate(normals[sel]) * n, axis=1)
        ok &= cosang >= np.cos(np.radians(cfg.max_normal_angle_deg))
    if cfg.rim_margin_mm is not None and rim_distance is not None:
        # the multiple registration passes ``rim_distance``, of each of ``points`` to its own surface's rim (mm)
        ok &= rim_distance[sel] >= cfg.rim_margin_mm
        if index.rim_tree is not None:
            k = np.nonzero(ok)[0]  # only the pairs still accepted are looked up
            ok[k] = index.rim_tree.query(p0[k], distance_upper_bound=cfg.rim_margin_mm)[0] >= cfg.rim_margin_mm
    k = np.nonzero(ok)[0]
    return sel[k], n[k], p0[k], d[k]


def icpatch(moving: PointSurface, fixed: PointSurface, initial: Transform | None = None,
            cfg: ICPatchConfig | None = None, index: PatchIndex | None = None) -> dict:
    """Register the points of ``moving`` to the patches of ``fixed``.

    Returns ``{"transform", "sigmas" (scale, omega, phi, kappa [rad], tx, ty, tz [mm]),
    "average_normal_distance_mm", "rms_normal_distance_mm", "matched_fraction", "pairs", "iterations",
    "converged"}``.
    """
    cfg = cfg or ICPatchConfig()
    T = initial or Transform.identity()
    if index is None:
        index = choose_patches(moving.points, moving.normals, patch_indices({"f": fixed}, cfg)["f"], T,
                               cfg.initial_distance_mm, cfg)[0]
    X = moving.points
    centre = X.mean(axis=0)
    dist = cfg.initial_distance_mm
    converged = False
    it = 0
    near = {}
    for it in range(1, cfg.max_iterations + 1):
        if it <= cfg.freeze_after:
            pairs_now = correspondences(X, moving.normals, index, T, dist, cfg, near)
        idx, n, p0, _ = pairs_now
        d = np.sum((T.apply(X[idx]) - p0) * n, axis=1)
        if len(idx) < 7:
            raise TooFewPairs(f"ICPatch: only {len(idx)} point-patch pairs within {dist:.1f} mm: "
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
        sd = rms * np.sqrt(np.abs(np.diag(np.linalg.inv(N))))
        negligible = bool(np.all(np.abs(dx) <= cfg.negligible_sigma * np.maximum(sd, 1e-15)))
        if negligible or (np.linalg.norm(w) < cfg.tol_rotation_rad and np.linalg.norm(dt) < cfg.tol_translation_mm
                          and abs(ds) < cfg.tol_scale):
            converged = True
            break
    idx, n, p0, d = correspondences(X, moving.normals, index, T, dist, cfg, near)
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
    return {"transform": T, "sigmas": {k: float(v) for k, v in zip(PARAMETER_NAMES, sig)},
            "average_normal_distance_mm": float(np.mean(np.abs(d))),
            "rms_normal_distance_mm": float(np.sqrt(np.mean(d ** 2))),
            "matched_fraction": float(len(idx) / len(X)), "pairs": int(len(idx)),
            "acceptance_distance_mm": float(dist), "iterations": it, "converged": converged}


def smooth_normals(surface: PointSurface, at: np.ndarray, tree=None, k: int = 30) -> np.ndarray:
    """Unit normals of the skin at the points ``at``: the plane of the surface's ``k`` nearest points.

    Turned like the nearest point's vertex normal (towards the viewer).
    """
    tree = tree or cKDTree(surface.points)
    k = min(k, len(surface.points))
    _, nb = tree.query(np.asarray(at), k=k)
    Q = surface.points[nb.reshape(len(at), k)]
    Q = Q - Q.mean(axis=1, keepdims=True)
    n = np.linalg.eigh(np.einsum("nki,nkj->nij", Q, Q))[1][:, :, 0]
    n[np.sum(n * surface.normals[nb.reshape(len(at), k)[:, 0]], axis=1) < 0] *= -1
    return n


def _subsample(n: int, max_points: int | None, seed: int = 0) -> np.ndarray:
    if max_points is None or n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


def neighbour_pairs(order: list) -> list:
    """Neighbouring arms around the rig's circle, the closing pair included."""
    if len(order) < 2:
        return []
    if len(order) == 2:
        return [(order[1], order[0])]
    return [(order[i], order[(i + 1) % len(order)]) for i in range(len(order))]


def chain_initial(surfaces: dict, order: list, reference: str, cfg: ICPatchConfig | None = None,
                  initial: dict | None = None, progress=lambda msg: None, indices: dict | None = None) -> tuple[dict, list]:
    """Initial transforms from pair-wise ICPatch, outward from the reference arm.

    Arms are placed one by one along the neighbouring pairs that overlap most
    under their nominal placement (``initial``, default identity: where the
    calibration put them), each registered to an already placed neighbour: a
    pair that barely overlaps is not needed to place every arm. An arm that no
    placed neighbour overlaps within ``cfg.initial_distance_mm`` is tried again
    at twice and four times that start distance (an arm that swung 1 deg about a
    pivot 2.5 m away has moved the skin by about 40 mm). Returns
    ``(transforms, pairwise results)``; arms no pair can reach are left out.
    """
    cfg = cfg or ICPatchConfig()
    start = {a: (initial or {}).get(a, Transform.identity()) for a in order}
    indices = indices or patch_indices({a: surfaces[a] for a in order}, cfg)  # (see patch_indices)

    def pairs_within(m, f, distance):  # m's points near f's patches under their nominal placement
        rel = start[f].inverse().compose(start[m])
        return _count_pairs(surfaces[m].points, surfaces[m].normals, indices[f][0], rel, distance, cfg)

    overlap = {(m, f): pairs_within(m, f, cfg.initial_distance_mm)
               for a, b in neighbour_pairs(order) for m, f in ((a, b), (b, a))}
    T = {reference: Transform.identity()}
    results = []
    pair_cfg = cfg
    while True:
        # the best-overlapping pair from a placed arm to an unplaced one (a maximum spanning tree)
        cand = [(n, m, f) for (m, f), n in overlap.items() if f in T and m not in T and n >= 7]
        if not cand and len(T) < len(order) and pair_cfg.initial_distance_mm < cfg.initial_distance_mm * 4:
            # no placed neighbour overlaps an unplaced arm within the acceptance distance: the arm moved more
            # than it allows (an arm that swings 1 deg about a pivot 2.5 m away moves the skin by 40 mm).
            # Widen the start distance for such arms, twice at most
            pair_cfg = replace(pair_cfg, initial_distance_mm=2 * pair_cfg.initial_distance_mm)
            overlap.update({(m, f): pairs_within(m, f, pair_cfg.initial_distance_mm)
                            for (m, f) in overlap if f in T and m not in T})
            continue
        if not cand:
            break
        n, arm, prev = max(cand)
        local = start[prev].inverse().compose(start[arm])  # the nominal placement, in prev's frame
        index, which = choose_patches(surfaces[arm].points, surfaces[arm].normals, indices[prev], local,
                                      pair_cfg.initial_distance_mm, cfg)
        moving = surfaces[arm]
        if cfg.chain_points is not None and len(moving.points) > cfg.chain_points:
            keep = np.zeros(len(moving.points), bool)
            keep[_subsample(len(moving.points), cfg.chain_points)] = True
            moving = subset(moving, keep)
        try:
            res = icpatch(moving, surfaces[prev], local, pair_cfg, index=index)
        except TooFewPairs:
            # the sampled count promised an overlap that the surface does not hold at this start distance (paper
            # scale, seed 31: arms swung by 31-38 mm, 2 pairs within 25 mm, the torso failed): this pair does not
            # place the arm at this distance; another pair, or a wider start, may
            progress(f"ICPatch {arm} to {prev}: too few pairs within {pair_cfg.initial_distance_mm:.0f} mm")
            overlap[(arm, prev)] = 0
            continue
        T[arm] = T[prev].compose(res["transform"])
        results.append({"a": arm, "b": prev, "patches": which, **{k: v for k, v in res.items() if k != "transform"}})
        progress(f"ICPatch {arm} to {prev}: {res['average_normal_distance_mm']:.3f} mm, "
                 f"{res['matched_fraction']:.0%} matched")
    return T, results


def _pair_blocks(a, b, x, foot, n, col, centres) -> list:
    """Jacobian blocks ``(column, J)`` of a pair's normal distances for its free arms.

    ``x``: the moving arm's points, ``foot``: their feet on the other arm's
    patches, ``n``: the patch normals (all in the reference frame, mm). Each
    arm's 7 parameters (scale, rotation, translation) act about its centre.
    """
    blocks = []
    if a in col:
        Ya = x - centres[a]
        blocks.append((col[a], np.column_stack([np.sum(n * Ya, axis=1), np.cross(Ya, n), n])))
    if b in col:
        Yb = foot - centres[b]
        blocks.append((col[b], -np.column_stack([np.sum(n * Yb, axis=1), np.cross(Yb, n), n])))
    return blocks


def observed_pairs(order: list, symmetric: bool = True) -> list:
    """The ``(moving, fixed)`` arm pairs the multiple registration observes: each neighbouring pair around the
    circle ``order`` (the closing one included), and with ``symmetric`` each also the other way round."""
    pairs = neighbour_pairs(order)
    if symmetric:
        # both directions of every pair: what is left of a bias (each surface's points against the other's
        # patches) pulls the two oppositely; the report's table keeps one row per neighbouring pair
        pairs = pairs + [(b, a) for a, b in pairs]
    return pairs


def pair_patch_sets(surfaces: dict, pairs: list, sample: dict, indices: dict, T: dict, dist: dict,
                    cfg: ICPatchConfig) -> tuple[dict, dict]:
    """Each pair's patch set (see :func:`choose_patches`): ``({pair: PatchIndex}, {pair: "compact" or "all"})``.

    ``sample``: each pair's observed points of its moving arm (ids); ``indices``:
    :func:`patch_indices` of the surfaces; ``T``: the arms' placements in the
    reference frame; ``dist``: each pair's acceptance distance (mm).
    """
    index, which = {}, {}
    for (a, b) in pairs:
        idx_all = sample[(a, b)]
        index[(a, b)], which[(a, b)] = choose_patches(
            surfaces[a].points[idx_all], surfaces[a].normals[idx_all], indices[b],
            T[b].inverse().compose(T[a]), dist[(a, b)], cfg)
    return index, which


def pair_residuals(X: np.ndarray, n_loc: np.ndarray, p0_loc: np.ndarray, T_moving: Transform,
                   T_fixed: Transform) -> tuple:
    """One pair's observations in the reference frame: ``(x, foot, n, d)``.

    ``X`` (N, 3): the moving arm's paired points in its own frame; ``n_loc``,
    ``p0_loc`` (N, 3): their patches' normals and the points of the patches
    under them in the fixed arm's frame (from :func:`correspondences`);
    ``T_moving``, ``T_fixed``: the two arms' placements in the reference
    frame. Returns the points ``x``, their feet on the patches, the patch
    normals (all (N, 3), reference frame, mm) and the normal distances
    ``d`` (N,, mm).
    """
    rel = T_fixed.inverse().compose(T_moving)
    d = np.sum((rel.apply(X) - p0_loc) * n_loc, axis=1) * T_fixed.scale
    x = T_moving.apply(X)
    n = T_fixed.rotate(n_loc)
    return x, x - d[:, None] * n, n, d


def normal_equations(observations: dict, col: dict, centres: dict, n_par: int, scale_weight: float,
                     pair_weight: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations ``N dx = rhs`` of the normal distances: ``(N (n_par, n_par), rhs (n_par,))``.

    ``observations``: ``{(a, b): (x, foot, n, d)}`` per pair (see
    :func:`pair_residuals`; ``d`` None: no right-hand side). Each free arm's
    7 parameters (scale, rotation [rad], translation [mm]) start at column
    ``col[arm]`` and act about ``centres[arm]`` (reference frame, mm); the
    reference arm has no columns. ``scale_weight`` on each scale's diagonal
    holds it (1e12: held where it is; 0: estimated). ``pair_weight``: a
    factor per pair (default 1).
    """
    N = np.zeros((n_par, n_par))
    rhs = np.zeros(n_par)
    for (a, b), (x, foot, n, d) in observations.items():
        w = 1.0 if pair_weight is None else pair_weight[(a, b)]
        blocks = _pair_blocks(a, b, x, foot, n, col, centres)
        for ca, Ja in blocks:
            if d is not None:
                rhs[ca:ca + 7] -= w * (Ja.T @ d)
            for cb, Jb in blocks:
                N[ca:ca + 7, cb:cb + 7] += w * (Ja.T @ Jb)
    for c in col.values():
        N[c, c] += scale_weight
    return N, rhs


def linked_arms(held_pairs: list, reference) -> set:
    """The arms that a chain of ``held_pairs`` (pairs observed in the adjustment) links to ``reference``."""
    linked, grew = {reference}, True
    while grew:
        grew = False
        for (a, b) in held_pairs:
            if (a in linked) != (b in linked):
                linked |= {a, b}
                grew = True
    return linked


def unit_weight_sigma(residuals, n_par: int) -> float:
    """A posteriori sigma of unit weight (mm): the normal distances' root sum of squares over the redundancy.

    ``residuals``: the normal distances (mm) of each pair, an iterable of arrays."""
    residuals = list(residuals)
    n_obs = sum(len(d) for d in residuals)
    return float(np.sqrt(sum(float(np.sum(d ** 2)) for d in residuals) / max(n_obs - n_par, 1)))


def corrections_negligible(dx: np.ndarray, N: np.ndarray, s0: float, negligible_sigma: float) -> bool:
    """Whether every correction ``dx`` is below ``negligible_sigma`` of its standard deviation (``s0`` times
    the root of ``N``'s inverse's diagonal): with few points the set of pairs keeps changing a little and the
    corrections jitter at that level, so they count as vanished there."""
    sd = s0 * np.sqrt(np.abs(np.diag(np.linalg.inv(N))))
    return bool(np.all(np.abs(dx) <= negligible_sigma * np.maximum(sd, 1e-15)))


def apply_corrections(T: dict, dx: np.ndarray, col: dict, centres: dict, cfg: ICPatchConfig) -> tuple[dict, float]:
    """The arms' placements after the corrections ``dx``, and the largest correction over its tolerance.

    Each free arm's correction (scale, rotation [rad], translation [mm], at
    ``col[arm]``) acts about its centre ``centres[arm]`` (reference frame):
    ``T'(x) = (1 + ds) dR (T(x) - c) + c + dt``. The second value is below 1
    when every correction is within ``cfg``'s convergence tolerances.
    """
    T = dict(T)
    biggest = 0.0
    for a, c0 in col.items():
        ds, w, dt = dx[c0], dx[c0 + 1:c0 + 4], dx[c0 + 4:c0 + 7]
        dR = rodrigues(w)
        c = centres[a]
        T[a] = Transform(T[a].scale * (1 + ds), dR @ T[a].R, (1 + ds) * dR @ (T[a].t - c) + c + dt)
        biggest = max(biggest, np.linalg.norm(w) / cfg.tol_rotation_rad, np.linalg.norm(dt) / cfg.tol_translation_mm,
                      abs(ds) / cfg.tol_scale)
    return T, biggest


def tightened_distances(dist: dict, residuals: dict, cfg: ICPatchConfig) -> dict:
    """Each pair's acceptance distance (mm) for the next iteration: ``tighten_k`` times the RMS of its normal
    distances (mm), never wider than before nor below ``min_distance_mm``; pairs without observations keep theirs."""
    out = dict(dist)
    for p, d in residuals.items():
        if len(d):
            out[p] = max(cfg.min_distance_mm, min(dist[p], cfg.tighten_k * float(np.sqrt(np.mean(d ** 2)))))
    return out


PARAMETER_NAMES = ("scale", "omega_rad", "phi_rad", "kappa_rad", "tx_mm", "ty_mm", "tz_mm")


def parameter_sigmas(N: np.ndarray, s0: float, col: dict) -> dict:
    """Each free arm's parameters' standard deviations ``{arm: {name: sigma}}`` (see ``PARAMETER_NAMES``) from
    the normal matrix ``N`` and the sigma of unit weight ``s0`` (mm)."""
    var = np.diag(s0 ** 2 * np.linalg.inv(N))
    return {a: dict(zip(PARAMETER_NAMES, map(float, np.sqrt(var[c:c + 7])))) for a, c in col.items()}


def geometric_strength(surfaces: dict, held_pairs: list, frozen: dict, sample: dict, T: dict, col: dict,
                       n_par: int, scale_weight: float, s0: float) -> dict:
    """How firmly the overlaps' shape holds each free arm (see :func:`arm_strength`): ``{arm: {...}}``.

    The adjustment's normal equations at the solution ``T`` with the skin's
    smoothed normals instead of each patch's. A patch's normal tilts with its
    vertices' noise (tiny preset: by ~0.1 rad), and those tilts seem to hold
    an arm even along a direction the skin leaves free (a plain cylinder's
    axis): the formal sigmas said 0.03 mm for an arm on plain-cylinder
    overlaps that slid 0.4 mm. Smoothed normals do not. ``frozen``: each
    pair's correspondences (see :func:`correspondences`) of the points
    ``sample`` of its moving arm; ``s0``: the sigma of unit weight (mm).
    """
    trees = {a: cKDTree(surfaces[a].points) for a in T}
    centres = {a: T[a].apply(surfaces[a].points.mean(axis=0)) for a in T}
    observations, k_of = {}, {}
    for (a, b) in held_pairs:
        # every k-th pair is enough for a covariance (scaled back by k); smoothing normals is costly
        k = max(1, len(frozen[(a, b)][0]) // 5000)
        idx, n_loc, p0_loc = (v[::k] for v in frozen[(a, b)][:3])
        X = surfaces[a].points[sample[(a, b)][idx]]
        rel = T[b].inverse().compose(T[a])
        xb = rel.apply(X)
        foot_b = xb - np.sum((xb - p0_loc) * n_loc, axis=1)[:, None] * n_loc
        n = T[b].rotate(smooth_normals(surfaces[b], foot_b, trees[b]))
        observations[(a, b)] = (T[a].apply(X), T[b].apply(foot_b), n, None)
        k_of[(a, b)] = k
    Ng = normal_equations(observations, col, centres, n_par, scale_weight, pair_weight=k_of)[0]
    cov = s0 ** 2 * np.linalg.pinv(Ng)
    return {a: arm_strength(cov[c:c + 7, c:c + 7], T[a].apply(surfaces[a].points), centres[a])
            for a, c in col.items()}


def fit_table(surfaces: dict, forward_pairs: list, residuals: dict, sample: dict, index: dict, which: dict,
              dist: dict, T: dict, cfg: ICPatchConfig) -> list:
    """The paper's Table 1: how the registered surfaces fit, one row per neighbouring pair (mm, fractions).

    Every point–patch pair at the solution ``T`` within the pair's final
    acceptance distance ``dist``, whichever of them the adjustment observed
    (``rim_margin_mm`` and the frozen set choose observations; they do not make
    the rest of the overlap unmatched). ``residuals``: the normal distances the
    adjustment observed per pair (empty: the pair was left out, and is not
    presented as fitting); ``sample``, ``index``, ``which``: each pair's
    observed points of its moving arm, its patch index and the name of that
    patch set.
    """
    loose = ICPatchConfig(max_normal_angle_deg=90.0, edge_margin=cfg.edge_margin)
    fit_cfg = replace(cfg, rim_margin_mm=None)
    rows = []
    for (a, b) in forward_pairs:
        d_adj = residuals[(a, b)]
        k_adj, n_all = len(d_adj), len(sample[(a, b)])
        idx_all = sample[(a, b)]
        X = surfaces[a].points[idx_all]
        rel = T[b].inverse().compose(T[a])
        # the overlap: points over the interior of a patch of b within a generous distance
        over_idx = correspondences(X, None, index[(a, b)], rel, cfg.overlap_distance_mm, loose)[0]
        over = len(over_idx)
        if k_adj:
            fit_idx, _, _, d = correspondences(X, surfaces[a].normals[idx_all], index[(a, b)], rel, dist[(a, b)],
                                               fit_cfg)
            d = d * T[b].scale
        else:
            fit_idx, d = np.zeros(0, np.int64), np.zeros(0)
        k = len(d)
        matched_in_overlap = int(np.isin(fit_idx, over_idx).sum())
        rows.append({"a": a, "b": b, "average_normal_distance_mm": float(np.mean(np.abs(d))) if k else None,
                     "rms_normal_distance_mm": float(np.sqrt(np.mean(d ** 2))) if k else None,
                     "matched_fraction": float(k / max(n_all, 1)),
                     "overlap_fraction": float(over / max(n_all, 1)),
                     "overlap_matched_fraction": float(matched_in_overlap / over) if over else 0.0,
                     "pairs": int(k), "adjustment_pairs": int(k_adj),
                     "adjustment_average_normal_distance_mm": float(np.mean(np.abs(d_adj))) if k_adj else None,
                     "acceptance_distance_mm": float(dist[(a, b)]), "patches": which[(a, b)]})
    return rows


def multi_surface_registration(surfaces: dict, order: list, reference: str, initial: dict,
                               cfg: ICPatchConfig | None = None, progress=lambda msg: None,
                               indices: dict | None = None) -> dict:
    """All surfaces in one least-squares adjustment, ``reference`` held fixed.

    Observations: the normal distances of every neighbouring pair's
    point–patch correspondences around the circle ``order`` (including the
    pair that closes it), so the misclosure of a chain of pair-wise results is
    spread over all pairs instead of piling up at the end. ``initial``: each
    arm's placement in the reference arm's frame (the pair-wise solution);
    ``indices``: :func:`patch_indices` of the surfaces, if already built.

    Steps: each pair's patch set (:func:`choose_patches`); then, until the
    corrections vanish, the pairs' correspondences (kept after
    ``freeze_after`` iterations), their residuals (:func:`pair_residuals`),
    the normal equations (:func:`normal_equations`), the corrections
    (:func:`apply_corrections`) and tighter acceptance distances; at the
    solution the parameters' sigmas, the arms' geometric strength
    (:func:`geometric_strength`) and Table 1 (:func:`fit_table`).

    Returns ``{"transforms": {arm: Transform}, "sigmas": {arm: {...}}, "strength": {arm: {...}}, "pairs":
    [{"a", "b", "average_normal_distance_mm", "matched_fraction", ...}], "iterations", "converged",
    "sigma0_mm", "left_out"}``.
    """
    cfg = cfg or ICPatchConfig()
    arms = list(order)
    free = [a for a in arms if a != reference]
    col = {a: 7 * i for i, a in enumerate(free)}
    n_par = 7 * len(free)
    pairs = observed_pairs(arms, cfg.symmetric)
    indices = indices or patch_indices({a: surfaces[a] for a in arms}, cfg)
    sample = {(a, b): _subsample(len(surfaces[a].points), cfg.max_points_per_pair, seed=k)
              for k, (a, b) in enumerate(pairs)}
    T = {a: initial.get(a, Transform.identity()) for a in arms}
    T[reference] = Transform.identity()
    # start from the pair-wise solution: its acceptance distances are already tight
    dist = {p: max(cfg.min_distance_mm, 2.0) for p in pairs}
    # each pair's patch set, chosen once at the start
    index, which = pair_patch_sets(surfaces, pairs, sample, indices, T, dist, cfg)
    near = {p: {} for p in pairs}
    # each observed point's distance to its own surface's rim (mm), where the rim rule asks for it
    rim_distance = {p: indices[p[0]][0].vertex_rim_distance[sample[p]] if cfg.rim_margin_mm is not None else None
                    for p in pairs}
    scale_weight = 0.0 if cfg.estimate_scale else 1e12
    converged, it, frozen, weak = False, 0, {}, set()
    for it in range(1, cfg.max_iterations + 1):
        centres = {a: T[a].apply(surfaces[a].points.mean(axis=0)) for a in arms}
        if it <= cfg.freeze_after:
            # every pair's closest-patch queries at once, on threads (Open3D and numpy release the GIL); after
            # these iterations the pairs are kept, so the adjustment converges instead of jittering as points
            # at the acceptance limit come and go
            def fresh(p):
                a, b = p
                return correspondences(surfaces[a].points[sample[p]], surfaces[a].normals[sample[p]], index[p],
                                       T[b].inverse().compose(T[a]), dist[p], cfg, near[p], rim_distance[p])
            with ThreadPoolExecutor(cores(cfg.threads)) as pool:
                frozen.update(zip(pairs, pool.map(fresh, pairs)))
        # a pair that barely overlaps says nothing reliable: it is left out (and reported)
        weak = {p for p in pairs if len(frozen[p][0]) < cfg.min_pairs}
        observations = {}
        for (a, b) in pairs:
            if (a, b) not in weak:
                idx, n_loc, p0_loc, _ = frozen[(a, b)]
                observations[(a, b)] = pair_residuals(surfaces[a].points[sample[(a, b)]][idx], n_loc, p0_loc,
                                                      T[a], T[b])
        residuals = {p: observations[p][3] if p in observations else np.zeros(0) for p in pairs}
        N, rhs = normal_equations(observations, col, centres, n_par, scale_weight)
        # every arm must hang on the reference through pairs that overlap
        unlinked = set(arms) - linked_arms([p for p in pairs if len(residuals[p])], reference)
        if unlinked:
            raise ValueError(f"arms {', '.join(sorted(unlinked))} are linked to the reference arm "
                             f"{reference} by no pair of surfaces that overlaps enough")
        dx = np.linalg.solve(N, rhs)
        negligible = corrections_negligible(dx, N, unit_weight_sigma(residuals.values(), n_par), cfg.negligible_sigma)
        T, biggest = apply_corrections(T, dx, col, centres, cfg)
        dist = tightened_distances(dist, residuals, cfg)
        if biggest < 1.0 or negligible:
            converged = True
            break
    # figures at the solution; covariance from the last normal equations
    s0 = unit_weight_sigma(residuals.values(), n_par)
    sig = parameter_sigmas(N, s0, col)
    strength = geometric_strength(surfaces, [p for p in pairs if p not in weak], frozen, sample, T, col, n_par,
                                  scale_weight, s0)
    pair_rows = fit_table(surfaces, neighbour_pairs(arms), residuals, sample, index, which, dist, T, cfg)
    for row in pair_rows:
        if row["pairs"]:
            progress(f"multiple registration {row['a']}-{row['b']}: {row['average_normal_distance_mm']:.3f} mm")
        else:
            progress(f"multiple registration {row['a']}-{row['b']}: left out, the surfaces barely overlap")
    return {"transforms": T, "sigmas": sig, "strength": strength, "pairs": pair_rows, "iterations": it,
            "converged": converged, "sigma0_mm": s0, "left_out": sorted(f"{a}-{b}" for a, b in weak)}


def arm_strength(cov: np.ndarray, points: np.ndarray, centre: np.ndarray, max_points: int = 5000) -> dict:
    """How firmly the adjustment holds one arm: its parameters' uncertainty along the weakest directions.

    ``cov`` is the arm's 7×7 covariance (scale, rotation [rad], translation
    [mm], increments about ``centre``), ``points`` the arm's surface in the
    reference frame. Figures (1 sigma): the translation along its weakest
    direction, the rotation about its weakest axis, and the largest position
    uncertainty of any of the arm's points (rotation's lever included), each
    with its direction (unit vector in the reference arm's frame).
    """
    cov = 0.5 * (cov + cov.T)
    lam, vec = np.linalg.eigh(cov[4:7, 4:7])
    t_sig, t_dir = float(np.sqrt(max(lam[-1], 0.0))), vec[:, -1]
    lam, vec = np.linalg.eigh(cov[1:4, 1:4])
    r_sig, r_axis = float(np.degrees(np.sqrt(max(lam[-1], 0.0)))), vec[:, -1]
    P = np.asarray(points)[_subsample(len(points), max_points)]
    Y = P - centre
    # d(point) = Y ds + w × Y + dt = [Y, -[Y]x, I] · (ds, w, dt)
    J = np.zeros((len(Y), 3, 7))
    J[:, :, 0] = Y
    J[:, 0, 2], J[:, 0, 3] = Y[:, 2], -Y[:, 1]
    J[:, 1, 1], J[:, 1, 3] = -Y[:, 2], Y[:, 0]
    J[:, 2, 1], J[:, 2, 2] = Y[:, 1], -Y[:, 0]
    J[:, :, 4:7] = np.eye(3)
    C = np.einsum("nij,jk,nlk->nil", J, cov, J)
    lam, vec = np.linalg.eigh(C)
    worst = int(np.argmax(lam[:, -1]))
    p_sig, p_dir = float(np.sqrt(max(lam[worst, -1], 0.0))), vec[worst, :, -1]

    def unit(v):
        v = np.asarray(v, float)
        return (v if v[np.argmax(np.abs(v))] >= 0 else -v).round(3).tolist()

    return {"translation_sigma_mm": t_sig, "translation_direction": unit(t_dir),
            "rotation_sigma_deg": r_sig, "rotation_axis": unit(r_axis),
            "position_sigma_mm": p_sig, "position_direction": unit(p_dir),
            "position_at": np.asarray(P[worst], float).round(1).tolist()}


def pair_fit(moving: PointSurface, fixed: PointSurface, T_moving: Transform, T_fixed: Transform,
             max_distance_mm: float = 2.0, cfg: ICPatchConfig | None = None) -> dict:
    """How well two placed surfaces fit: average normal distance (mm) and matched fraction of ``moving``."""
    cfg = cfg or ICPatchConfig()
    rel = T_fixed.inverse().compose(T_moving)
    # all patches: the same measure whichever patches a registration used
    idx, _, _, d = correspondences(moving.points, moving.normals, PatchIndex(fixed), rel,
                                   max_distance_mm, cfg)
    d = d * T_fixed.scale
    return {"average_normal_distance_mm": float(np.mean(np.abs(d))) if len(d) else None,
            "signed_mean_mm": float(np.mean(d)) if len(d) else None,
            "matched_fraction": float(len(idx) / max(len(moving.points), 1))}


def _axis_name(v) -> str:
    v = np.asarray(v, float)
    k = int(np.argmax(np.abs(v)))
    return f"({v[0]:.2f}, {v[1]:.2f}, {v[2]:.2f}), mostly {'xyz'[k]}"


def weak_arms(strength: dict, surfaces: dict, cfg: ICPatchConfig | None = None) -> dict:
    """Arms the adjustment does not hold firmly: ``{arm: problem}`` naming the weak direction.

    ``strength`` is :func:`multi_surface_registration`'s (per arm, from
    :func:`arm_strength`); the limit is ``max_position_sigma_factor`` times
    the median precision of the arm's points.
    """
    cfg = cfg or ICPatchConfig()
    out = {}
    for a, st in strength.items():
        own = float(np.median(surfaces[a].data["sigma_mm"])) if "sigma_mm" in (surfaces[a].data or {}) else 0.1
        limit = cfg.max_position_sigma_factor * own
        if not np.isfinite(st["position_sigma_mm"]) or st["position_sigma_mm"] > limit:
            out[a] = (f"arm {a} is not held by its overlaps: its surface can move {st['position_sigma_mm']:.2f} mm "
                      f"(1 sigma) along {_axis_name(st['position_direction'])} > {limit:.2f} mm "
                      f"({cfg.max_position_sigma_factor:g} x its points' precision {own:.2f} mm); weakest "
                      f"translation {st['translation_sigma_mm']:.2f} mm along {_axis_name(st['translation_direction'])}, "
                      f"rotation {st['rotation_sigma_deg']:.3f} deg about {_axis_name(st['rotation_axis'])}")
    return out
