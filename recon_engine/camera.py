"""The camera model: OpenCV's pinhole camera with Brown–Conrady distortion.

Exactly the model of ``cv2.projectPoints`` with ``distCoeffs = [k1, k2, p1, p2,
k3]`` (capture-format spec, conventions). Frames and units:

- world: right-handed, millimetres;
- camera: ``x_cam = R @ (X - C)``, +z along the optical axis, x right, y down;
- normalized image: ``(x_cam / z_cam, y_cam / z_cam)``, unitless;
- pixel: x right, y down, centre of the top-left pixel at (0, 0).

Everything here is a pure function of numpy arrays; inputs are never modified.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = [
    "Camera",
    "distort",
    "undistort",
    "project",
    "pixel_to_ray",
    "rotation_to_opk",
    "opk_to_rotation",
    "photogrammetric_iop",
]


@dataclass(frozen=True)
class Camera:
    """Interior (IOP) and exterior (EOP) orientation of one camera.

    Attributes
    ----------
    width, height : int
        Image size (px).
    fx, fy : float
        Focal length (px).
    cx, cy : float
        Principal point (px).
    dist : (5,) array
        ``[k1, k2, p1, p2, k3]`` (OpenCV's order).
    R : (3, 3) array
        Rotation world→camera.
    C : (3,) array
        Perspective centre in world coordinates (mm).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    C: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        object.__setattr__(self, "dist", _as_array(self.dist, (5,), "dist"))
        object.__setattr__(self, "R", _as_array(self.R, (3, 3), "R"))
        object.__setattr__(self, "C", _as_array(self.C, (3,), "C"))

    @property
    def K(self) -> np.ndarray:
        """Camera matrix (px)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def rvec(self) -> np.ndarray:
        """Rodrigues vector of R (world→camera), for OpenCV."""
        import cv2

        return cv2.Rodrigues(self.R)[0].ravel()

    @property
    def tvec(self) -> np.ndarray:
        """Translation ``t = -R @ C`` (mm), for OpenCV."""
        return -self.R @ self.C

    def with_pose(self, R, C) -> "Camera":
        """The same IOPs with another EOP (world→camera ``R``, centre ``C`` in mm)."""
        return replace(self, R=np.asarray(R, float).copy(), C=np.asarray(C, float).copy())

    def project(self, X) -> np.ndarray:
        """Pixel coordinates (N, 2) of world points ``X`` (N, 3) in mm."""
        return project(self, X)

    def rays(self, uv) -> np.ndarray:
        """Unit ray directions (N, 3) in the world frame for pixels ``uv`` (N, 2)."""
        return pixel_to_ray(self, uv)

    def to_dict(self) -> dict:
        """The camera as the spec's ``calibration.json`` entry."""
        return {
            "width": int(self.width),
            "height": int(self.height),
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "dist": [float(v) for v in self.dist],
            "R": [[float(v) for v in row] for row in self.R],
            "C": [float(v) for v in self.C],
        }


def _as_array(value, shape, name):
    arr = np.array(value, dtype=float)
    if arr.shape != shape:
        raise ValueError(f"camera {name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"camera {name} holds a non-finite value")
    arr.setflags(write=False)
    return arr


def distort(xy, dist) -> np.ndarray:
    """Apply Brown–Conrady distortion to normalized image coordinates.

    Parameters
    ----------
    xy : (N, 2) array
        Ideal normalized coordinates (unitless).
    dist : (5,) array
        ``[k1, k2, p1, p2, k3]``.

    Returns
    -------
    (N, 2) array of distorted normalized coordinates, as ``cv2.projectPoints``
    computes them.
    """
    xy = np.asarray(xy, dtype=float)
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=float)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def distort_jacobian(x, y, dist):
    """Partial derivatives of the distorted coordinates wrt the ideal ones."""
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dxd_dx = radial + 2.0 * x * x * dradial_dr2 + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * x * y * dradial_dr2 + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = 2.0 * x * y * dradial_dr2 + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = radial + 2.0 * y * y * dradial_dr2 + 6.0 * p1 * y + 2.0 * p2 * x
    return dxd_dx, dxd_dy, dyd_dx, dyd_dy


def undistort(xy_distorted, dist, iterations: int = 30, tol: float = 1e-14, initial=None) -> np.ndarray:
    """Invert :func:`distort` by Newton's method.

    Starts from the distorted coordinates and refines every point with the
    analytic Jacobian until the update is below ``tol`` (normalized units, far
    below 1e-9 px). Unlike ``cv2.undistortPoints``' fixed-point iteration it
    converges in the frame corners under strong distortion too.

    Parameters
    ----------
    xy_distorted : (N, 2) array
        Distorted normalized coordinates.
    dist : (5,) array
        ``[k1, k2, p1, p2, k3]``.

    initial : (N, 2) array, optional
        A close first guess (e.g. interpolated from a coarse grid); Newton's
        quadratic convergence then needs one or two steps.

    Returns
    -------
    (N, 2) array of ideal normalized coordinates.
    """
    target = np.asarray(xy_distorted, dtype=float)
    dist = np.asarray(dist, dtype=float)
    xy = target.copy() if initial is None else np.array(initial, dtype=float)
    if not np.any(dist):
        return target.copy()
    x, y = xy[..., 0].copy(), xy[..., 1].copy()
    tx, ty = target[..., 0], target[..., 1]
    for _ in range(iterations):
        xd = distort(np.stack([x, y], axis=-1), dist)
        a, b, c, d = distort_jacobian(x, y, dist)
        rx, ry = xd[..., 0] - tx, xd[..., 1] - ty
        det = a * d - b * c
        dx = (d * rx - b * ry) / det
        dy = (a * ry - c * rx) / det
        x -= dx
        y -= dy
        if max(np.max(np.abs(dx), initial=0.0), np.max(np.abs(dy), initial=0.0)) <= tol:
            break
    return np.stack([x, y], axis=-1)


def project(camera: Camera, X) -> np.ndarray:
    """Project world points to pixels, exactly as ``cv2.projectPoints``.

    Parameters
    ----------
    camera : Camera
    X : (N, 3) array
        World points (mm).

    Returns
    -------
    (N, 2) array of pixel coordinates. Points behind the camera are projected
    too (as OpenCV does); check depth with :func:`camera_depth` where it matters.
    """
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    xc = (X - camera.C) @ camera.R.T
    xy = xc[:, :2] / xc[:, 2:3]
    xyd = distort(xy, camera.dist)
    return np.column_stack([camera.fx * xyd[:, 0] + camera.cx, camera.fy * xyd[:, 1] + camera.cy])


def camera_depth(camera: Camera, X) -> np.ndarray:
    """Depth (mm) of world points along the camera's optical axis."""
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    return (X - camera.C) @ camera.R[2]


def pixel_to_normalized(camera: Camera, uv, initial=None, iterations: int = 30) -> np.ndarray:
    """Ideal (undistorted) normalized coordinates (N, 2) of pixels ``uv`` (N, 2).

    ``initial`` is an optional close guess of the result (see :func:`undistort`).
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    xyd = np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy])
    return undistort(xyd, camera.dist, iterations=iterations, initial=initial)


def undistortion_grid(camera: Camera, step: int = 8):
    """Ideal normalized coordinates on a grid every ``step`` px covering the frame.

    Returns ``(grid_x, grid_y)``, two float32 (rows, cols) maps with node
    (i, j) at pixel (j * step - step, i * step - step): a lookup table for
    first guesses of :func:`pixel_to_normalized` over a whole image.
    """
    us = np.arange(-step, camera.width + 2 * step, step, dtype=float)
    vs = np.arange(-step, camera.height + 2 * step, step, dtype=float)
    uu, vv = np.meshgrid(us, vs)
    xy = pixel_to_normalized(camera, np.column_stack([uu.ravel(), vv.ravel()]))
    return xy[:, 0].reshape(uu.shape).astype(np.float32), xy[:, 1].reshape(uu.shape).astype(np.float32)


def normalized_to_pixel(camera: Camera, xy) -> np.ndarray:
    """Pixels (N, 2) of ideal normalized coordinates ``xy`` (N, 2), with distortion."""
    xyd = distort(np.asarray(xy, dtype=float).reshape(-1, 2), camera.dist)
    return np.column_stack([camera.fx * xyd[:, 0] + camera.cx, camera.fy * xyd[:, 1] + camera.cy])


def pixel_to_ray(camera: Camera, uv) -> np.ndarray:
    """Unit direction (N, 3) in the world frame of the ray through each pixel.

    The ray starts at the perspective centre ``camera.C`` and passes through
    the scene point imaged at ``uv`` (px), lens distortion removed.
    """
    xy = pixel_to_normalized(camera, uv)
    d_cam = np.column_stack([xy, np.ones(len(xy))])
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    return d_cam @ camera.R  # R^T @ d for each row


# --- photogrammetric terms -------------------------------------------------

# OpenCV's camera frame (x right, y down, looking along +z) against the
# photogrammetric image frame (x right, y up, looking along -z).
_CV_TO_PHOTO = np.diag([1.0, -1.0, -1.0])


def rotation_to_opk(R) -> np.ndarray:
    """Omega, phi, kappa (degrees) of a world→camera rotation in OpenCV's frame.

    The photogrammetric rotation ``M = diag(1, -1, -1) @ R`` (world→image space,
    image y up, camera looking along -z) is written ``M = Rz(kappa) @ Ry(phi) @
    Rx(omega)`` with the passive elementary rotations of the photogrammetric
    literature (Kraus; Wolf and Dewitt), the sequential omega-phi-kappa
    convention: the object frame is rotated first about X by omega, then about
    the once-rotated Y by phi, then about the twice-rotated Z by kappa.
    """
    M = _CV_TO_PHOTO @ np.asarray(R, dtype=float)
    # M = R3(k) R2(p) R1(o): M[2,0] = sin(phi), M[2,1] = -sin(o)cos(p),
    # M[2,2] = cos(o)cos(p), M[1,0] = -sin(k)cos(p), M[0,0] = cos(k)cos(p).
    phi = np.arcsin(np.clip(M[2, 0], -1.0, 1.0))
    omega = np.arctan2(-M[2, 1], M[2, 2])
    kappa = np.arctan2(-M[1, 0], M[0, 0])
    return np.degrees([omega, phi, kappa])


def opk_to_rotation(omega_deg, phi_deg, kappa_deg) -> np.ndarray:
    """World→camera rotation in OpenCV's frame from omega, phi, kappa (degrees).

    The inverse of :func:`rotation_to_opk`.
    """
    o, p, k = np.radians([omega_deg, phi_deg, kappa_deg])
    r1 = np.array([[1, 0, 0], [0, np.cos(o), np.sin(o)], [0, -np.sin(o), np.cos(o)]])
    r2 = np.array([[np.cos(p), 0, -np.sin(p)], [0, 1, 0], [np.sin(p), 0, np.cos(p)]])
    r3 = np.array([[np.cos(k), np.sin(k), 0], [-np.sin(k), np.cos(k), 0], [0, 0, 1]])
    M = r3 @ r2 @ r1
    return _CV_TO_PHOTO @ M


def photogrammetric_iop(camera: Camera, pixel_size_mm: float) -> dict:
    """The interior orientation in the terms photogrammetrists read.

    Returns principal distance ``c`` in mm and px, the principal point offset
    ``(xp, yp)`` in mm from the image centre (photogrammetric axes: x right,
    y up), the same offset in px (OpenCV axes), the aspect ratio ``fy / fx``,
    and the distortion coefficients unchanged.
    """
    centre_x = (camera.width - 1) / 2.0
    centre_y = (camera.height - 1) / 2.0
    dx_px = camera.cx - centre_x
    dy_px = camera.cy - centre_y
    c_px = 0.5 * (camera.fx + camera.fy)
    return {
        "principal_distance_px": c_px,
        "principal_distance_mm": c_px * pixel_size_mm,
        "principal_point_offset_px": [dx_px, dy_px],
        "principal_point_offset_mm": [dx_px * pixel_size_mm, -dy_px * pixel_size_mm],
        "aspect_ratio": camera.fy / camera.fx,
        "dist": [float(v) for v in camera.dist],
    }
