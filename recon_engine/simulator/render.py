"""Physically based image formation for the simulated rig.

For every pixel, ``supersample``² rays are traced through the camera's own
lens (:mod:`.lens`, the simulator's model, richer than the engine's: each
sub-pixel position is inverted exactly to its ray by Newton's method)
into an Open3D ``RaycastingScene``. At each hit: smooth (interpolated) normal,
albedo (slowly varying skin, printed markers, dim walls), and irradiance from
ambient room light, an optional key light and every pattern projector that
sees the point (a shadow ray decides), with Lambert's cosine, inverse-square
fall-off, projector defocus and the blur of light diffusing in skin. The
sub-samples are averaged (pixel integration), then the camera applies
depth-dependent defocus, lens blur, cos⁴ vignetting, photo-response
non-uniformity, shot and read noise and 8-bit quantization.

Everything is vectorized over rays; the only Python loops run over chunks of
image rows, projectors and blur levels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from ..o3d import o3d

from ..camera import Camera
from ..imaging import sample_bilinear
from .config import CameraConfig, ProjectorConfig
from .lens import Lens, inverse_grid, pixel_to_normalized_fast
from .testfield import Tower, tower_albedo

LUT_STEP = 8  # px between nodes of the inverse-distortion lookup table
RAYS_PER_CHUNK = 1_500_000  # bounds the memory of one ray-casting call
SHADOW_EPS_MM = 1.0  # a shadow-ray hit this close before the point still lights it


@dataclass
class Surface:
    """One object of the scene, in world coordinates (mm)."""

    kind: str  # "skin", "tower", "wall" or "floor"
    vertices: np.ndarray
    triangles: np.ndarray
    albedo: np.ndarray | None = None  # per vertex; None for the tower (printed)
    tower: Tower | None = None
    pose: tuple | None = None  # tower: (R, t) with X_world = R @ X_tower + t
    marks: object | None = None  # skin: a skin.SkinMarks multiplying the albedo, looked up at the rest position
    rest: np.ndarray | None = None  # skin with marks: each vertex's position on the rest body (mm)
    normals: np.ndarray = field(init=False)
    triangle_albedo: np.ndarray | None = field(init=False, default=None)

    def __post_init__(self):
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                         o3d.utility.Vector3iVector(self.triangles))
        mesh.compute_vertex_normals()
        self.normals = np.asarray(mesh.vertex_normals).copy()
        if self.albedo is not None:
            self.triangle_albedo = self.albedo[self.triangles].mean(axis=1)


@dataclass(frozen=True)
class Lighting:
    ambient: float
    key: float = 0.0
    key_direction: tuple = (0.3, -0.2, 1.0)  # towards the key light
    projectors: tuple = ()  # rig.Projector
    projector_cfg: ProjectorConfig | None = None


class Scene:
    """A ray-casting scene of surfaces, with shading lookups per hit."""

    def __init__(self, surfaces: list[Surface]):
        self.surfaces = surfaces
        self.raycast = o3d.t.geometry.RaycastingScene()
        for s in surfaces:
            mesh = o3d.t.geometry.TriangleMesh()
            mesh.vertex.positions = o3d.core.Tensor(s.vertices.astype(np.float32))
            mesh.triangle.indices = o3d.core.Tensor(s.triangles.astype(np.int32))
            self.raycast.add_triangles(mesh)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        """First hits of rays (N, 3) from ``origins`` (N, 3) or (3,) along unit ``directions``."""
        n = len(directions)
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = directions
        out = {k: [] for k in ("t_hit", "geometry_ids", "primitive_ids", "primitive_uvs", "primitive_normals")}
        for start in range(0, n, RAYS_PER_CHUNK):
            r = self.raycast.cast_rays(o3d.core.Tensor(rays[start:start + RAYS_PER_CHUNK]))
            for k in out:
                out[k].append(r[k].numpy())
        return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}

    def distance(self, origins, directions) -> np.ndarray:
        """Distance (mm) to the first hit along each ray; inf where nothing is hit."""
        return self.cast(origins, directions)["t_hit"].astype(float)

    def visible(self, viewpoint, points, eps_mm: float = SHADOW_EPS_MM) -> np.ndarray:
        """Whether each point (N, 3) is seen from ``viewpoint`` (3,) unoccluded."""
        vec = np.asarray(points, float) - viewpoint
        d = np.linalg.norm(vec, axis=1)
        t = self.distance(np.asarray(viewpoint, float), vec / d[:, None])
        return t > d - eps_mm

    def shade_inputs(self, hits: dict, origins, directions):
        """Positions, unit normals and albedo at the hits; ``valid`` marks real hits.

        Smooth surfaces (skin) get normals and albedo interpolated from their
        vertices; flat ones (tower, walls) the triangle's normal.
        """
        t = hits["t_hit"]
        valid = np.isfinite(t)
        pos = np.asarray(origins, float) + directions * np.where(valid, t, 0.0)[:, None]
        normal = hits["primitive_normals"].astype(float)
        albedo = np.zeros(len(t))
        gid = hits["geometry_ids"]
        pid = hits["primitive_ids"].astype(np.int64)
        for g, s in enumerate(self.surfaces):
            sel = np.flatnonzero(valid & (gid == g))
            if not len(sel):
                continue
            if s.kind == "tower":
                R, tt = s.pose
                P_tower = (pos[sel] - tt) @ R
                face = pid[sel] // 2
                on_side = face < s.tower.n_faces
                a = np.full(len(sel), 0.3)  # caps and stand: grey
                a[on_side] = tower_albedo(s.tower, face[on_side], P_tower[on_side])
                albedo[sel] = a
            elif s.kind == "skin":
                tri = s.triangles[pid[sel]]
                uv = hits["primitive_uvs"][sel].astype(float)
                w = np.column_stack([1.0 - uv.sum(axis=1), uv])  # barycentric
                n = np.einsum("ij,ijk->ik", w, s.normals[tri])
                normal[sel] = n / np.linalg.norm(n, axis=1, keepdims=True)
                albedo[sel] = np.einsum("ij,ij->i", w, s.albedo[tri])
                if s.marks is not None:
                    albedo[sel] *= s.marks.sample(np.einsum("ij,ijk->ik", w, s.rest[tri]))
            else:
                albedo[sel] = s.triangle_albedo[pid[sel]]
        # shade the side the ray hits (back faces of thin shells)
        flip = np.einsum("ij,ij->i", normal, directions) > 0
        normal[flip] *= -1
        return pos, normal, albedo, valid


def _pattern_levels(pattern: np.ndarray, sigmas) -> list:
    return [cv2.GaussianBlur(pattern, (0, 0), s, borderType=cv2.BORDER_CONSTANT) for s in sigmas]


PATTERN_SIGMAS = np.array([0.35, 0.6, 1.0, 1.6, 2.5, 4.0])  # projector px


def _interp_levels(sigma, levels_sigma):
    """Indices and weights to blend two precomputed blur levels for ``sigma``."""
    s = np.clip(sigma, levels_sigma[0], levels_sigma[-1])
    hi = np.clip(np.searchsorted(levels_sigma, s), 1, len(levels_sigma) - 1)
    lo = hi - 1
    w = (s - levels_sigma[lo]) / (levels_sigma[hi] - levels_sigma[lo])
    return lo, hi, w


class PreparedLighting:
    """Lighting with each projector's blurred pattern levels computed once."""

    def __init__(self, lighting: Lighting, subsurface_mm: float = 0.0):
        self.lighting = lighting
        self.subsurface_mm = subsurface_mm
        self.levels = [_pattern_levels(p.pattern, PATTERN_SIGMAS) for p in lighting.projectors]

    def irradiance(self, scene: Scene, pos, normal, valid, kinds, viewpoint=None, specular: float = 0.0,
                   shininess: float = 30.0):
        """Irradiance at the hits, and the radiance of the projectors' highlights on skin seen from ``viewpoint``.

        The highlight is Blinn-Phong's normalised lobe (``shininess``) carrying
        the share ``specular`` of a projector's light that the skin's oily film
        reflects; it is added to albedo x irradiance, and is zero where
        ``specular`` is 0.

        Returns
        -------
        E, S : (N,) arrays, irradiance and highlight radiance (same units as albedo x irradiance)
        """
        L = self.lighting
        E = np.where(valid, L.ambient, 0.0)
        S = np.zeros(len(E))
        if L.key:
            kd = np.asarray(L.key_direction, float)
            kd /= np.linalg.norm(kd)
            E += L.key * np.clip(normal @ kd, 0, None) * valid
        pc = L.projector_cfg
        hit = np.flatnonzero(valid)
        pos32 = pos[hit].astype(np.float32)
        nrm32 = normal[hit].astype(np.float32)
        for proj, levels in zip(L.projectors, self.levels):
            m = proj.model
            rel = pos32 - m.C.astype(np.float32)  # projector -> point
            xc = rel @ m.R.T.astype(np.float32)
            facing = np.einsum("ij,ij->i", nrm32, rel) < 0
            sel = np.flatnonzero(facing & (xc[:, 2] > 1.0))
            xc, rel = xc[sel], rel[sel]
            u = m.fx * xc[:, 0] / xc[:, 2] + m.cx
            v = m.fy * xc[:, 1] / xc[:, 2] + m.cy
            inside = (u > -2) & (u < m.width + 1) & (v > -2) & (v < m.height + 1)
            sel, xc, rel, u, v = sel[inside], xc[inside], rel[inside], u[inside], v[inside]
            d = np.sqrt(np.einsum("ij,ij->i", rel, rel))
            cosine = -np.einsum("ij,ij->i", nrm32[sel], rel) / d
            idx = hit[sel]
            if len(idx) == 0:
                continue
            lit = scene.visible(m.C, pos[idx])
            idx, xc, u, v, d, cosine = idx[lit], xc[lit], u[lit], v[lit], d[lit], cosine[lit]
            # blur of the pattern on the surface: projector optics (depth of
            # field) and, on skin, light diffusing under the surface
            defocus = pc.defocus_px_per_mm * (pc.width / 1024.0) * np.abs(xc[:, 2] - pc.focus_mm)
            px_mm = xc[:, 2] / m.fx  # size of a projector pixel on the surface (mm)
            sss = np.where(kinds[idx], self.subsurface_mm / px_mm, 0.0)
            sigma = np.sqrt(pc.blur_sigma_px ** 2 + defocus ** 2 + sss ** 2)
            lo, hi, w = _interp_levels(sigma, PATTERN_SIGMAS)
            ui, vi = u, v
            value = np.zeros(len(idx))
            for k, level in enumerate(levels):
                use = (lo == k) | (hi == k)
                if not use.any():
                    continue
                sample = sample_bilinear(level, ui[use], vi[use])
                weight = np.where(lo[use] == k, 1.0 - w[use], w[use])
                value[use] += weight * sample
            emitted = pc.black_level + (1.0 - pc.black_level) * value
            E[idx] += pc.power * emitted * cosine * (pc.distance_mm / d) ** 2
            if specular > 0 and viewpoint is not None:
                incident = pc.power * emitted * (pc.distance_mm / d) ** 2
                skin = kinds[idx]
                to_light = -rel[lit] / d[:, None]
                to_eye = np.asarray(viewpoint, np.float32) - pos32[sel[lit]]
                to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
                half = to_light + to_eye
                half /= np.linalg.norm(half, axis=1, keepdims=True)
                n_h = np.clip(np.einsum("ij,ij->i", nrm32[sel[lit]], half), 0.0, None)
                lobe = (shininess + 8.0) / 8.0 * n_h ** shininess
                S[idx] += np.where(skin, specular * incident * lobe * cosine, 0.0)
        return E, S


def render(scene: Scene, camera: Camera, lighting: PreparedLighting, cc: CameraConfig,
           rng: np.random.Generator, exposure: float, prnu_seed: int = 0, lens: Lens | None = None,
           specular: float = 0.0, shininess: float = 30.0):
    """Render one 8-bit image (height, width) of ``scene`` seen by ``camera``.

    Parameters
    ----------
    camera : Camera
        Image size and pose (``R``, ``C``); its interior orientation is used
        only when ``lens`` is not given.
    lens : Lens, optional
        The true lens the rays are traced through (default: the camera's
        five OpenCV terms as a :class:`Lens`).
    exposure : float
        Radiance (albedo x irradiance) that fills 80% of the full well.
    specular, shininess : float
        Oily skin's highlights of the projectors' light (:meth:`PreparedLighting.irradiance`); 0: matte skin.
    prnu_seed : int
        Seeds the camera's fixed photo-response non-uniformity.

    Returns
    -------
    image : (height, width) uint8
    depth : (height, width) float32, mean depth (mm) along the optical axis; inf on misses
    """
    H, W, ss = camera.height, camera.width, cc.supersample
    rows_per_chunk = max(1, RAYS_PER_CHUNK // (W * ss * ss))
    radiance = np.zeros((H, W), np.float64)
    depth = np.zeros((H, W), np.float64)
    kinds = np.array([s.kind == "skin" for s in scene.surfaces])
    cells = np.arange(ss) / ss - 0.5
    lens = lens if lens is not None else Lens.from_camera(camera)
    lut = inverse_grid(lens, W, H, LUT_STEP)
    for r0 in range(0, H, rows_per_chunk):
        r1 = min(H, r0 + rows_per_chunk)
        # stratified jittered sub-samples: a regular grid would quantize the
        # position of edges aligned with the pixel grid (a coherent bias of up
        # to a quarter pixel along a whole marker edge); jitter makes the pixel
        # an unbiased estimate of the area integral
        vv = (np.arange(r0, r1)[:, None, None, None] + cells[None, :, None, None]
              + rng.random((r1 - r0, ss, W, ss)) / ss)
        uu = (np.arange(W)[None, None, :, None] + cells[None, None, None, :]
              + rng.random((r1 - r0, ss, W, ss)) / ss)
        uv = np.column_stack([uu.ravel(), vv.ravel()])
        # the inverse of the true lens: Newton from a guess interpolated on a grid (exact to ~1e-6 px)
        xy = pixel_to_normalized_fast(lens, uv, lut, LUT_STEP)
        d_cam = np.column_stack([xy, np.ones(len(xy))])
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        dirs = d_cam @ camera.R
        hits = scene.cast(camera.C, dirs)
        pos, normal, albedo, valid = scene.shade_inputs(hits, camera.C, dirs)
        is_skin = valid & kinds[np.where(valid, hits["geometry_ids"], 0).astype(np.int64)]
        E, S = lighting.irradiance(scene, pos, normal, valid, is_skin, camera.C, specular, shininess)
        L = albedo * E + S
        z = np.where(valid, hits["t_hit"] * d_cam[:, 2], 1e5)
        shape = (r1 - r0, ss, W, ss)
        radiance[r0:r1] = L.reshape(shape).mean(axis=(1, 3))
        depth[r0:r1] = z.reshape(shape).mean(axis=(1, 3))
    # --- optics: defocus (depth of field) and lens blur, blended per pixel
    f_mm = lens.fx * (cc.pixel_size_mm)
    coc_mm = f_mm ** 2 / (cc.f_number * (cc.focus_mm - f_mm)) * np.abs(depth - cc.focus_mm) / depth
    sigma = np.sqrt(cc.blur_sigma_px ** 2 + (coc_mm / cc.pixel_size_mm / 4.0) ** 2)
    blur_sigmas = np.array([cc.blur_sigma_px, 0.8, 1.2, 1.8, 2.6, 3.6, 5.0])
    blur_sigmas = np.unique(np.maximum(blur_sigmas, cc.blur_sigma_px))
    lo, hi, w = _interp_levels(sigma, blur_sigmas)
    img = np.zeros_like(radiance)
    for k, s in enumerate(blur_sigmas):
        use = (lo == k) | (hi == k)
        if use.any():
            blurred = cv2.GaussianBlur(radiance, (0, 0), s, borderType=cv2.BORDER_REFLECT)
            img[use] += np.where(lo[use] == k, 1.0 - w[use], w[use]) * blurred[use]
    # --- sensor
    if cc.vignetting:
        jj, ii = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        r2 = ((jj - lens.cx) / lens.fx) ** 2 + ((ii - lens.cy) / lens.fy) ** 2
        img /= (1.0 + r2) ** 2
    prnu = np.random.default_rng(prnu_seed).normal(1.0, cc.prnu, (H, W))
    electrons = np.clip(img * prnu / exposure * 0.8 * cc.full_well_e, 0, None)
    electrons = rng.poisson(electrons).astype(float) + rng.normal(0, cc.read_noise_e, (H, W))
    dn = electrons / cc.full_well_e * 255.0 + cc.black_level_dn
    image = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
    return image, np.where(depth >= 1e5, np.inf, depth).astype(np.float32)
