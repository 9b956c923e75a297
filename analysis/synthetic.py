"""Scan-like point clouds of a known surface, and synthetic backs with known indices (tests, validation).

``scan_surface`` samples a triangle mesh (e.g. the simulator's posed body)
the way the rig would measure it: points spread over the skin, noise along
the normal (default 0.07 mm, the reconstruction's measured precision) and
holes where fewer than two cameras of any arm see the skin. It replaces a
render and a reconstruction where only the analysis is under test.
"""

from __future__ import annotations

import numpy as np

from .torso import Torso, make_torso


def rig_cameras(n_arms: int = 4, per_arm: int = 5, radius_mm: float = 2500.0, spacing_mm: float = 800.0,
                height_mm: float = 1070.0, first_azimuth_deg: float = 45.0, yaw_deg: float = 0.0) -> np.ndarray:
    """Camera centres (arms, cameras, 3) of the simulator's rig layout (world frame, mm)."""
    step = np.degrees(spacing_mm / radius_mm)
    out = np.zeros((n_arms, per_arm, 3))
    for k in range(n_arms):
        az0 = first_azimuth_deg + yaw_deg + 360.0 * k / n_arms
        for j in range(per_arm):
            az = np.radians(az0 + (j - (per_arm - 1) / 2) * step)
            out[k, j] = [radius_mm * np.cos(az), radius_mm * np.sin(az), height_mm]
    return out


def scan_surface(vertices: np.ndarray, triangles: np.ndarray, region: np.ndarray | None = None, n_points: int = 60_000,
                 noise_mm: float = 0.07, cameras: np.ndarray | None = None, max_incidence_deg: float = 70.0,
                 seed: int = 0, min_cameras: int = 2) -> Torso:
    """Points sampled on the triangles ``region`` (bool mask, default all) of a closed mesh, as the rig sees them.

    Area-uniform samples; a sample is kept when at least ``min_cameras`` cameras of one
    arm (``cameras``: (arms, per arm, 3), default :func:`rig_cameras`) see it unoccluded by
    the whole mesh, within ``max_incidence_deg`` of its normal. Then Gaussian noise of
    ``noise_mm`` along the normal. Returns a :class:`Torso` with outward normals.
    """
    from recon_engine.o3d import o3d

    rng = np.random.default_rng(seed)
    V, T = np.asarray(vertices, float), np.asarray(triangles, np.int64)
    Tr = T if region is None else T[np.asarray(region, bool)]
    a, b, c = V[Tr[:, 0]], V[Tr[:, 1]], V[Tr[:, 2]]
    cr = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    # oversample: visibility removes part of them
    m = int(n_points * 1.6)
    f = rng.choice(len(Tr), m, p=area / area.sum())
    r1, r2 = rng.random(m), rng.random(m)
    s = np.sqrt(r1)
    P = (1 - s)[:, None] * a[f] + (s * (1 - r2))[:, None] * b[f] + (s * r2)[:, None] * c[f]
    N = cr[f] / np.maximum(np.linalg.norm(cr[f], axis=1, keepdims=True), 1e-12)
    cams = rig_cameras() if cameras is None else np.asarray(cameras, float)
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(V.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(T.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    # orient the normals outward: a short ray along the normal must leave the closed mesh
    probe = np.concatenate([P + 0.5 * N, N], axis=1).astype(np.float32)
    hits = scene.count_intersections(o3d.core.Tensor(probe)).numpy()
    N[hits % 2 == 1] *= -1
    cos_max = np.cos(np.radians(max_incidence_deg))
    # each camera's line of sight to each sample: unoccluded, and at what angle to the normal
    clear = np.zeros((cams.shape[0], cams.shape[1], len(P)), bool)
    cosine = np.zeros(clear.shape)
    for a, arm in enumerate(cams):
        for c, C in enumerate(arm):
            v = C - P
            dist = np.linalg.norm(v, axis=1)
            v /= dist[:, None]
            rays = np.concatenate([P + 0.2 * v, v], axis=1).astype(np.float32)
            clear[a, c] = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() >= dist - 1.0
            cosine[a, c] = np.sum(v * N, axis=1)
    # a camera that sees the skin sees its outer side: the normal turns towards the cameras with a clear line of
    # sight. Where the mesh passes through itself (crossed forearms, an arm pressed into the flank) the parity
    # test above flips normals, and a reconstruction would never (its normals face the cameras that saw them)
    towards = np.sign(np.sum(np.where(clear, cosine, 0.0), axis=(0, 1)))
    flip = towards < 0
    N[flip] *= -1
    cosine[:, :, flip] *= -1
    seen = ((clear & (cosine >= cos_max)).sum(axis=1) >= min_cameras).any(axis=0)
    P, N = P[seen], N[seen]
    if len(P) > n_points:
        keep = rng.choice(len(P), n_points, replace=False)
        P, N = P[keep], N[keep]
    P = P + rng.normal(0, noise_mm, len(P))[:, None] * N
    return make_torso(P, N)


def synthetic_back(rotation_deg: float = 0.0, lateral_mm: float = 0.0, hump_mm: float = 0.0, apex: float = 0.6,
                   imbalance_mm: float = 0.0, length_mm: float = 480.0, z_sp_mm: float = 850.0, spacing_mm: float = 3.0,
                   noise_mm: float = 0.0, seed: int = 0):
    """A superelliptic trunk with a known curve: (Torso, truth dict).

    Each horizontal section (superellipse of exponent 4, half axes 150 mm across, 100 mm deep, a spinal groove
    on the back) is shifted towards the patient's right by ``lateral_mm·b(s)`` plus
    ``imbalance_mm·s`` and turned about a spine 45 mm under the back skin by
    ``rotation_deg·b(s)`` (positive: the right back comes backwards), with a hump of
    ``hump_mm·b(s)`` on the right back 70 mm from the spine, where ``b`` is a
    bump of height 1 at level ``apex`` (SP = 0, VP = 1) and 0 at both ends.
    Frame: the simulator's (faces -Y, left +X, Z up); SP at ``z_sp_mm``. A neck
    (narrow cylinder, its back coming 8 mm backwards again towards the occiput from 50 mm above VP) stands above
    VP and a pelvis widens below SP so the landmarks can be found.
    """
    rng = np.random.default_rng(seed)
    z0, z1 = z_sp_mm - 80.0, z_sp_mm + length_mm + 90.0
    zs = np.arange(z0, z1, spacing_mm)
    pts, nrm = [], []
    for z in zs:
        s = (z - z_sp_mm) / length_mm
        b = np.cos(0.5 * np.pi * np.clip(np.where(s < apex, (apex - s) / apex, (s - apex) / (1 - apex)), 0, 1)) ** 2
        b = np.where((s < 0) | (s > 1), 0.0, b)
        # section shape: trunk, narrowing into the neck above VP, a sacral bulge below SP
        # the trunk narrows into the neck: half the shoulders' width exactly at VP (s = 1)
        neck = np.clip((s - 1.0) / 0.08 + 0.75, 0, 1)
        a_half = 150.0 * (1 - neck) + 50.0 * neck
        d_half = 100.0 * (1 - neck) + 50.0 * neck
        # the sacral prominence at SP, the lumbar lordosis above it
        bulge = 12.0 * np.exp(-0.5 * (s / 0.06) ** 2) - 8.0 * np.exp(-0.5 * ((s - 0.3) / 0.15) ** 2)
        # a superelliptic section (exponent 4): a broad, flat back as the MakeHuman body has;
        # sampled evenly across (x) on the back and the front, and evenly up (y) on the flanks
        n_x = max(40, int(2 * a_half / spacing_mm))
        xa = np.linspace(-a_half, a_half, n_x)
        ya = d_half * np.clip(1 - np.abs(xa / a_half) ** 4, 0, None) ** 0.25
        yf = np.linspace(-0.8 * d_half, 0.8 * d_half, max(10, int(1.6 * d_half / spacing_mm)))
        xf = a_half * np.clip(1 - np.abs(yf / d_half) ** 4, 0, None) ** 0.25
        x = np.concatenate([xa, xa, xf, -xf])
        y = np.concatenate([ya, -ya, yf, yf])
        th = np.arctan2(y, x)
        n_around = len(x)
        back = np.clip(np.sin(th), 0, None)
        # the back of the head: the neck's skin comes backwards again towards the occiput, so the neck's
        # hollow (cervical lordosis) is seen as a hollow above VP
        occiput = 8.0 * np.clip((s - 1.10) / 0.08, 0, 1)
        y = y + back ** 2 * (bulge + occiput - 4.0 * np.exp(-0.5 * (x / 14.0) ** 2))
        # hump on the right back (-X), 70 mm from the spine
        y = y + hump_mm * b * np.exp(-0.5 * ((x + 70.0) / 35.0) ** 2) * back ** 2
        spine_y = d_half + bulge * 0 - 45.0
        rel = np.column_stack([x, y - spine_y])
        phi = -np.radians(rotation_deg * b)
        c, sn = np.cos(phi), np.sin(phi)
        xr = c * rel[:, 0] - sn * rel[:, 1]
        yr = sn * rel[:, 0] + c * rel[:, 1] + spine_y
        xr = xr - lateral_mm * b - imbalance_mm * np.clip(s, 0, 1.06)
        pts.append(np.column_stack([xr, yr, np.full(n_around, z)]))
    P = np.vstack(pts)
    if noise_mm:
        P = P + rng.normal(0, noise_mm, P.shape)
    # this trunk is star-shaped about its vertical axis: the rule "away from the axis" orients its normals
    from .torso import estimate_normals, orient_outward

    torso = make_torso(P, orient_outward(P, estimate_normals(P)))
    truth = {"vertebra_prominens_z": z_sp_mm + length_mm, "sacral_point_z": z_sp_mm, "rotation_deg": rotation_deg,
             "lateral_mm": lateral_mm, "hump_mm": hump_mm, "imbalance_mm": imbalance_mm, "apex_z": z_sp_mm + apex * length_mm}
    return torso, truth
