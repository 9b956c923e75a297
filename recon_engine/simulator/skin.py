"""What real skin carries beyond the smooth albedo: freckles, moles, body hair, a tattoo, underwear.

The marks live in a texture wrapped round the rest body on a vertical
cylinder about the spine (arc length at ``RADIUS_MM`` across, height up), so
they move with the skin through posture, sway and breathing. The texture holds
a multiplier of the skin's albedo: below 1 for pigment and hair, above 1 for
white fabric. Lengths in mm, rest-body frame (the subject faces -Y, left +X,
the back is +Y).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..imaging import sample_bilinear
from .bodies import Body
from .config import ConditionsConfig

RADIUS_MM = 150.0  # the cylinder's radius: arc lengths across the texture are measured on it
TEXEL_MM = 0.25  # texture resolution: a hair's width is a fraction of a texel, as of a camera pixel (0.32 mm)
AA_SHIFT = 4  # OpenCV's fractional bits for drawing at sub-texel positions
FABRIC_ALBEDO = 0.75  # white cotton
WAISTBAND_MM = 25.0  # the elastic band at the top of the underwear, darker and printed
FABRIC_MM = 1.0  # the fabric's thickness over the skin (the waistband's step in the surface)


@dataclass(frozen=True)
class SkinMarks:
    """A multiplier of the skin's albedo on a cylinder about the rest body's spine."""

    texture: np.ndarray  # (rows, cols) float32: row = height, col = arc length from the front seam
    centre: tuple  # (x, y) of the cylinder's axis, mm
    z0: float  # height of row 0, mm

    def sample(self, rest_points: np.ndarray) -> np.ndarray:
        """The multiplier at rest-body points (N, 3), mm; 1 outside the texture."""
        p = np.asarray(rest_points, float)
        theta = np.arctan2(p[:, 0] - self.centre[0], p[:, 1] - self.centre[1])  # 0 at the middle of the back
        col = (theta + np.pi) * RADIUS_MM / TEXEL_MM
        row = (p[:, 2] - self.z0) / TEXEL_MM
        return sample_bilinear(self.texture, col, row, border="constant", value=1.0).astype(float)


def _canvas(shape) -> np.ndarray:
    return np.zeros(shape, np.uint8)


def _fixed(points) -> np.ndarray:
    return np.rint(np.asarray(points) * (1 << AA_SHIFT)).astype(np.int32)


def make_skin_marks(body: Body, cond: ConditionsConfig, rng: np.random.Generator,
                    skin_albedo_mean: float) -> SkinMarks | None:
    """The marks ``cond`` asks for on ``body`` (None when it asks for none).

    ``skin_albedo_mean`` converts the fabric's albedo into a multiplier of the
    skin's. Each kind of mark is drawn with anti-aliasing into its own 8-bit
    coverage layer (255: the texel fully covered), then the layers multiply.
    """
    wanted = (cond.freckles_per_dm2 > 0 or cond.moles > 0 or cond.body_hair_per_cm2 > 0 or cond.tattoo
              or cond.underwear_top_mm is not None)
    if not wanted:
        return None
    centre = tuple(body.spine[:, :2].mean(axis=0))
    z0, z1 = body.z_sacrum - 250.0, body.z_c7 + 150.0
    rows, cols = int(np.ceil((z1 - z0) / TEXEL_MM)), int(np.ceil(2 * np.pi * RADIUS_MM / TEXEL_MM))
    texture = np.ones((rows, cols), np.float32)
    area_mm2 = (z1 - z0) * 2 * np.pi * RADIUS_MM

    def layer(draw, darkness: float):
        cover = _canvas((rows, cols))
        draw(cover)
        texture[...] *= 1.0 - darkness * cover.astype(np.float32) / 255.0

    def uniform_points(n):
        return np.column_stack([rng.uniform(0, cols, n), rng.uniform(0, rows, n)])

    if cond.freckles_per_dm2 > 0:
        n = rng.poisson(cond.freckles_per_dm2 * area_mm2 / 1e4)
        centres, radii = uniform_points(n), rng.uniform(0.5, 1.5, n) / TEXEL_MM
        shades = rng.uniform(0.15, 0.4, n)  # how much darker than the skin around

        def freckles(cover):
            for c, r, s in zip(_fixed(centres), _fixed(radii), shades):
                cv2.circle(cover, tuple(int(v) for v in c), int(r), int(255 * s / 0.4), -1, cv2.LINE_AA, AA_SHIFT)
            cover[...] = cv2.GaussianBlur(cover, (0, 0), 0.3 / TEXEL_MM)
        layer(freckles, 0.4)
    if cond.moles > 0:
        centres, radii = uniform_points(cond.moles), rng.uniform(1.5, 3.0, cond.moles) / TEXEL_MM

        def moles(cover):
            for c, r in zip(_fixed(centres), _fixed(radii)):
                cv2.circle(cover, tuple(int(v) for v in c), int(r), 255, -1, cv2.LINE_AA, AA_SHIFT)
        layer(moles, 0.65)
    if cond.body_hair_per_cm2 > 0:
        n = rng.poisson(cond.body_hair_per_cm2 * area_mm2 / 100.0)
        start = uniform_points(n)
        length = rng.uniform(5.0, 15.0, n) / TEXEL_MM
        # hair grows downwards and outwards from the spine, with a gentle curl
        side = np.sign(start[:, 0] - cols / 2)
        angle = np.radians(90.0 + side * rng.uniform(10, 50, n))[:, None] + np.linspace(0, 1, 6)[None, :] * \
            rng.normal(0, 0.4, n)[:, None]
        steps = np.stack([np.cos(angle), np.sin(angle)], axis=2) * (length / 5)[:, None, None]
        strands = start[:, None, :] + np.concatenate([np.zeros((n, 1, 2)), np.cumsum(steps[:, :5], axis=1)], axis=1)
        # 0.06 mm strands cover a quarter of a 0.25 mm texel: drawn 1 texel wide at a quarter of the darkness
        coverage = min(1.0, 0.06 / TEXEL_MM)

        def hair(cover):
            cv2.polylines(cover, list(_fixed(strands)), False, 255, 1, cv2.LINE_AA, AA_SHIFT)
        layer(hair, 0.85 * coverage)
    if cond.tattoo:
        def tattoo(cover):
            # a tribal band: thick smooth curves, a ring and filled leaves, ~120 x 90 mm on the back
            cx = cols / 2 + rng.uniform(-60, 60) / TEXEL_MM
            cy = (body.z_sacrum + rng.uniform(0.3, 0.8) * (body.z_c7 - body.z_sacrum) - z0) / TEXEL_MM
            half_w, half_h = 60.0 / TEXEL_MM, 45.0 / TEXEL_MM
            t = np.linspace(0, 1, 60)
            for k in range(5):
                phase, amp = rng.uniform(0, 2 * np.pi), rng.uniform(0.3, 0.9)
                x = cx + half_w * (2 * t - 1)
                y = cy + half_h * amp * np.sin(2 * np.pi * (1.2 * t) + phase) * (1 - 0.5 * k / 5)
                thick = int(rng.uniform(2.0, 6.0) / TEXEL_MM)
                cv2.polylines(cover, [_fixed(np.column_stack([x, y]))], False, 255, thick, cv2.LINE_AA, AA_SHIFT)
            cv2.ellipse(cover, _fixed((cx, cy)).tolist(), _fixed((0.35 * half_w, 0.35 * half_w)).tolist(),
                        0, 0, 360, 255, int(4 / TEXEL_MM), cv2.LINE_AA, AA_SHIFT)
            for k in range(6):
                a = 2 * np.pi * k / 6
                centre_k = (cx + 0.7 * half_w * np.cos(a), cy + 0.7 * half_h * np.sin(a))
                cv2.ellipse(cover, _fixed(centre_k).tolist(), _fixed((8 / TEXEL_MM, 3 / TEXEL_MM)).tolist(),
                            np.degrees(a), 0, 360, 255, -1, cv2.LINE_AA, AA_SHIFT)
        layer(tattoo, 0.8)
    if cond.underwear_top_mm is not None:
        top_row = (body.z_sacrum + cond.underwear_top_mm - z0) / TEXEL_MM
        band_row = top_row - WAISTBAND_MM / TEXEL_MM
        r = np.arange(rows)[:, None]
        fabric = np.clip(top_row - r + 0.5, 0.0, 1.0)  # 1 below the top edge, a texel's ramp at it
        texture *= (1.0 - fabric) + fabric * (FABRIC_ALBEDO / skin_albedo_mean)
        band = _canvas((rows, cols))
        # the waistband: dark elastic with light printed blocks (a brand name) every 40 mm
        lo, hi = int(max(band_row, 0)), int(max(top_row, 0))
        band[lo:hi] = 255
        for x0 in np.arange(0, cols, 40.0 / TEXEL_MM):
            cv2.rectangle(band, (int(x0), int(band_row + 8 / TEXEL_MM)),
                          (int(x0 + 18 / TEXEL_MM), int(top_row - 8 / TEXEL_MM)), 0, -1)
        texture *= 1.0 - 0.7 * band.astype(np.float32) / 255.0
    return SkinMarks(texture=texture, centre=centre, z0=z0)


def clothe(body: Body, cond: ConditionsConfig) -> Body:
    """The body with the underwear's fabric over the skin below its top edge (``FABRIC_MM`` outwards)."""
    if cond.underwear_top_mm is None:
        return body
    from ..o3d import o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(body.vertices),
                                     o3d.utility.Vector3iVector(body.triangles))
    mesh.compute_vertex_normals()
    normals = np.asarray(mesh.vertex_normals)
    top = body.z_sacrum + cond.underwear_top_mm
    covered = np.clip((top - body.vertices[:, 2]) / 1.0 + 0.5, 0.0, 1.0)  # the step, over a millimetre
    # the legs and arms are not covered; the torso's lower part is (hips and buttocks)
    covered *= (np.abs(body.vertices[:, 0] - body.spine[:, 0].mean()) < 250.0)
    return replace(body, vertices=body.vertices + FABRIC_MM * covered[:, None] * normals)
