"""The simulator's own lens: richer than the engine's camera model, and independent of it.

The renderer traces every pixel's ray through this model; nothing here calls
the engine's distortion code (``recon_engine.camera``'s ``distort`` /
``undistort``), so calibrating the engine on simulated images meets a lens its
model does not describe exactly (issue 29, §1).

Forward model, ideal normalized coordinates ``(x, y) = (x_cam / z, y_cam / z)``
to pixels (x right, y down, centre of the top-left pixel at (0, 0))::

    r2     = x² + y²
    radial = 1 + k1 r2 + k2 r2² + k3 r2³
    D      = 1 + p3 r2                                  (Brown's decentring profile)
    xd = x radial + [2 p1 x y + p2 (r2 + 2 x²)] D + s1 r2 + s2 r2²
    yd = y radial + [p1 (r2 + 2 y²) + 2 p2 x y] D + s3 r2 + s4 r2²
    u  = fx xd + skew yd + cx
    v  = fy yd + cy

With ``p3 = s1..s4 = skew = 0`` this is OpenCV's five-term model (and
``cv2.projectPoints``); ``s1..s4`` are OpenCV's thin-prism terms (its
12-coefficient model), so both parts can be checked against OpenCV. The
engine's model holds ``fx, fy, cx, cy, k1, k2, p1, p2, k3``; ``p3``, the
thin prism and the skew are what it cannot represent.

The inverse (pixel → ray) is Newton's method on this forward model with its
analytic Jacobian, from a guess interpolated on a coarse grid that was itself
inverted to convergence; vectorized over all rays.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from ..imaging import sample_bilinear

ENGINE_TERMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
EXTRA_TERMS = ("p3", "s1", "s2", "s3", "s4", "skew")


@dataclass(frozen=True)
class Lens:
    """Interior orientation of one simulated camera (px and unitless)."""

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    p3: float = 0.0  # Brown's higher-order decentring: the p1/p2 terms scaled by (1 + p3 r²)
    s1: float = 0.0  # thin prism (OpenCV's s1..s4): x += s1 r² + s2 r⁴, y += s3 r² + s4 r⁴
    s2: float = 0.0
    s3: float = 0.0
    s4: float = 0.0
    skew: float = 0.0  # px: u = fx xd + skew yd + cx

    @classmethod
    def from_camera(cls, camera) -> "Lens":
        """The lens of an engine ``Camera`` (its five OpenCV terms; read as numbers only)."""
        k1, k2, p1, p2, k3 = (float(v) for v in camera.dist)
        return cls(float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy),
                   k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)

    @property
    def dist5(self) -> np.ndarray:
        """The engine's (OpenCV's) five terms ``[k1, k2, p1, p2, k3]``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_extra_terms(self) -> bool:
        """Whether the lens has terms the engine's model lacks."""
        return any(getattr(self, k) != 0.0 for k in EXTRA_TERMS)

    def to_dict(self) -> dict:
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "Lens":
        return cls(**{k: float(v) for k, v in d.items() if k in cls.__dataclass_fields__})

    def with_changes(self, **kw) -> "Lens":
        return replace(self, **kw)


def _terms(lens: Lens, x, y, jacobian: bool):
    """Distorted ``(xd, yd)`` and, when asked, the Jacobian ``(a, b, c, d)`` sharing one evaluation."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (lens.k1 + r2 * (lens.k2 + r2 * lens.k3))
    xy2 = 2.0 * x * y
    tx = lens.p1 * xy2 + lens.p2 * (r2 + 2.0 * x * x)
    ty = lens.p1 * (r2 + 2.0 * y * y) + lens.p2 * xy2
    dscale = 1.0 + lens.p3 * r2 if lens.p3 else 1.0
    xd = x * radial + tx * dscale
    yd = y * radial + ty * dscale
    prism = lens.s1 or lens.s2 or lens.s3 or lens.s4
    if prism:
        xd += r2 * (lens.s1 + lens.s2 * r2)
        yd += r2 * (lens.s3 + lens.s4 * r2)
    if not jacobian:
        return xd, yd
    dradial = lens.k1 + r2 * (2.0 * lens.k2 + 3.0 * lens.k3 * r2)  # d radial / d r2
    cross = xy2 * dradial + (2.0 * lens.p1 * x + 2.0 * lens.p2 * y) * dscale
    a = radial + 2.0 * x * x * dradial + (2.0 * lens.p1 * y + 6.0 * lens.p2 * x) * dscale
    b = cross.copy() if np.ndim(cross) else cross
    c = cross
    d = radial + 2.0 * y * y * dradial + (6.0 * lens.p1 * y + 2.0 * lens.p2 * x) * dscale
    if lens.p3:
        a = a + 2.0 * lens.p3 * x * tx
        b = b + 2.0 * lens.p3 * y * tx
        c = c + 2.0 * lens.p3 * x * ty
        d = d + 2.0 * lens.p3 * y * ty
    if prism:
        ax = 2.0 * (lens.s1 + 2.0 * lens.s2 * r2)  # 2 d prism_x / d r2
        ay = 2.0 * (lens.s3 + 2.0 * lens.s4 * r2)
        a = a + x * ax
        b = b + y * ax
        c = c + x * ay
        d = d + y * ay
    return xd, yd, a, b, c, d


def distort(lens: Lens, xy) -> np.ndarray:
    """Distorted normalized coordinates (N, 2) of ideal ones ``xy`` (N, 2)."""
    xy = np.asarray(xy, dtype=float)
    xd, yd = _terms(lens, xy[..., 0], xy[..., 1], jacobian=False)
    return np.stack([xd, yd], axis=-1)


def distort_jacobian(lens: Lens, x, y):
    """``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)`` of :func:`distort`, analytic."""
    return _terms(lens, np.asarray(x, float), np.asarray(y, float), jacobian=True)[2:]


def normalized_to_pixel(lens: Lens, xy) -> np.ndarray:
    """Pixels (N, 2) of ideal normalized coordinates ``xy`` (N, 2): the forward model."""
    xyd = distort(lens, np.asarray(xy, dtype=float).reshape(-1, 2))
    return np.column_stack([lens.fx * xyd[:, 0] + lens.skew * xyd[:, 1] + lens.cx,
                            lens.fy * xyd[:, 1] + lens.cy])


def pixel_to_distorted(lens: Lens, uv) -> np.ndarray:
    """Distorted normalized coordinates (N, 2) of pixels ``uv`` (N, 2) (the affine part inverted)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    yd = (uv[:, 1] - lens.cy) / lens.fy
    xd = (uv[:, 0] - lens.cx - lens.skew * yd) / lens.fx
    return np.column_stack([xd, yd])


def pixel_to_normalized(lens: Lens, uv, initial=None, tol: float = 1e-15, max_iterations: int = 50) -> np.ndarray:
    """Ideal normalized coordinates (N, 2) of pixels ``uv`` (N, 2): Newton on :func:`distort`.

    ``initial`` is an optional close first guess (e.g. from :func:`inverse_grid`);
    iterations stop when every update is below ``tol`` (normalized units; 1e-15
    is about 1e-11 px at the paper's 7 400 px focal length) or after
    ``max_iterations`` (with ``tol=0``: exactly that many steps).
    """
    target = pixel_to_distorted(lens, uv)
    xy = target.copy() if initial is None else np.array(initial, dtype=float).reshape(-1, 2)
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    tx, ty = target[:, 0], target[:, 1]
    for _ in range(max_iterations):
        xd, yd, a, b, c, d = _terms(lens, x, y, jacobian=True)
        rx, ry = xd - tx, yd - ty
        det = a * d - b * c
        dx = (d * rx - b * ry) / det
        dy = (a * ry - c * rx) / det
        x -= dx
        y -= dy
        if tol > 0 and max(np.max(np.abs(dx), initial=0.0), np.max(np.abs(dy), initial=0.0)) <= tol:
            break
    return np.stack([x, y], axis=-1)


def inverse_grid(lens: Lens, width: int, height: int, step: int = 8):
    """Ideal normalized coordinates on nodes every ``step`` px over the frame (and one step beyond).

    Returns a float32 (rows, cols, 2) map of ``(x, y)`` with node (i, j) at
    pixel ``(j * step - step, i * step - step)``: first guesses for
    :func:`pixel_to_normalized` over a whole image.
    """
    us = np.arange(-step, width + 2 * step, step, dtype=float)
    vs = np.arange(-step, height + 2 * step, step, dtype=float)
    uu, vv = np.meshgrid(us, vs)
    xy = pixel_to_normalized(lens, np.column_stack([uu.ravel(), vv.ravel()]))
    return np.dstack([xy[:, 0].reshape(uu.shape), xy[:, 1].reshape(uu.shape)]).astype(np.float32)


def guess_from_grid(grid, uv, step: int = 8) -> np.ndarray:
    """Bilinear interpolation of :func:`inverse_grid` at pixels ``uv`` (N, 2), edges replicated.

    OpenCV's remap of the two maps at once: fast, positions rounded to 1/32 of
    a grid cell, so the guess is off by up to about ``step / 64`` px; one
    Newton step from it is exact to about 1e-6 px (see
    :func:`pixel_to_normalized_fast`).
    """
    maps = grid if isinstance(grid, np.ndarray) else np.dstack(grid).astype(np.float32)
    uv = np.asarray(uv, dtype=float)
    g = sample_bilinear(maps, (uv[:, 0] + step) / step, (uv[:, 1] + step) / step, border="replicate")
    return g.astype(float)


def pixel_to_normalized_fast(lens: Lens, uv, grid, step: int = 8, iterations: int = 1) -> np.ndarray:
    """The renderer's inversion: :func:`guess_from_grid`, then ``iterations`` Newton steps.

    Newton converges quadratically: from a guess within 0.13 px one step
    leaves at most 5e-7 px (measured on a strong lens with every term at paper
    scale, ``tests/test_simulator_lens.py``), a second 1e-12 px at 40 % more
    rendering time; one is the default.
    """
    return pixel_to_normalized(lens, uv, initial=guess_from_grid(grid, uv, step), tol=0.0, max_iterations=iterations)


def project(lens: Lens, R, C, X) -> np.ndarray:
    """Pixels (N, 2) of world points ``X`` (N, 3) for a camera ``x_cam = R @ (X - C)`` with this lens."""
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    xc = (X - np.asarray(C, float)) @ np.asarray(R, float).T
    return normalized_to_pixel(lens, xc[:, :2] / xc[:, 2:3])


def rays(lens: Lens, R, uv, initial=None) -> np.ndarray:
    """Unit ray directions (N, 3) in the world frame through pixels ``uv`` (N, 2)."""
    xy = pixel_to_normalized(lens, uv, initial=initial)
    d = np.column_stack([xy, np.ones(len(xy))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d @ np.asarray(R, float)


def engine_residual_px(lens: Lens, width: int, height: int, n: int = 41) -> dict:
    """How far the lens's extra terms move image points over the frame (px).

    Compares this lens with the same lens stripped to the engine's terms, on a
    grid of ideal points covering the frame: the model error a calibration
    holding the *true* engine-model values would leave (before the adjustment
    absorbs part of it into the other terms).
    """
    us, vs = np.meshgrid(np.linspace(0, width - 1, n), np.linspace(0, height - 1, n))
    xy = pixel_to_normalized(lens, np.column_stack([us.ravel(), vs.ravel()]))
    plain = replace(lens, **{k: 0.0 for k in EXTRA_TERMS})
    d = np.linalg.norm(normalized_to_pixel(lens, xy) - normalized_to_pixel(plain, xy), axis=1)
    return {"rms_px": float(np.sqrt(np.mean(d ** 2))), "max_px": float(d.max())}


def true_lenses(calibration) -> dict:
    """Camera id -> :class:`Lens` of a simulated truth calibration.

    The whole lens from each camera's ``simulator_lens`` key where the truth
    has one, else the lens of the camera's engine terms (scenarios written
    before the key existed).
    """
    extra = (calibration.extra or {}).get("camera_extra", {}) or {}
    out = {}
    for cam_id, cam in calibration.cameras.items():
        d = (extra.get(cam_id) or {}).get("simulator_lens")
        out[cam_id] = Lens.from_dict(d) if d else Lens.from_camera(cam)
    return out
