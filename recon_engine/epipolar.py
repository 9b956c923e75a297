"""Epipolar resampling of a pair of calibrated images.

Both images of a pair are resampled onto one common image plane parallel to
the baseline (``x`` along the baseline), so conjugate points lie on the same
row. The rectified cameras keep the original perspective centres and a
common principal distance; only the rotation and the principal points change.
Every rectified coordinate maps back to the original image exactly
(float64, through the original lens distortion), so measurements made in
the rectified images are intersected in original image coordinates.

Frames: ``R`` of a camera is world→camera; the rectification rotation
``R_rect`` is world→rectified camera and is shared by both images.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Camera, distort, pixel_to_normalized


@dataclass(frozen=True)
class RectifiedPair:
    """Geometry of one epipolar-resampled pair.

    Attributes
    ----------
    left, right : Camera
        The original cameras (IOPs and EOPs).
    R_rect : (3, 3) array
        World→rectified-camera rotation, common to both images.
    f : float
        Principal distance of the rectified images (px).
    c_left, c_right : (2,) array
        Principal points of the rectified images (px); same row coordinate.
    size : (int, int)
        Width and height of each rectified image (px).
    """

    left: Camera
    right: Camera
    R_rect: np.ndarray
    f: float
    c_left: np.ndarray
    c_right: np.ndarray
    size: tuple

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.right.C - self.left.C))

    def _side(self, side: str):
        if side == "left":
            return self.left, self.c_left
        if side == "right":
            return self.right, self.c_right
        raise ValueError(f"side must be 'left' or 'right', not {side!r}")

    def to_original(self, side: str, uv_rect) -> np.ndarray:
        """Original (distorted) pixel coordinates of rectified ones (N, 2) px."""
        cam, c = self._side(side)
        uv = np.asarray(uv_rect, dtype=float).reshape(-1, 2)
        rays = np.column_stack([(uv - c) / self.f, np.ones(len(uv))])
        d = rays @ (cam.R @ self.R_rect.T).T  # rectified frame → camera frame
        xy = d[:, :2] / d[:, 2:3]
        xyd = distort(xy, cam.dist)
        return np.column_stack([cam.fx * xyd[:, 0] + cam.cx, cam.fy * xyd[:, 1] + cam.cy])

    def to_rectified(self, side: str, uv) -> np.ndarray:
        """Rectified pixel coordinates of original (distorted) ones (N, 2) px."""
        cam, c = self._side(side)
        xy = pixel_to_normalized(cam, np.asarray(uv, dtype=float).reshape(-1, 2))
        d = np.column_stack([xy, np.ones(len(xy))]) @ (self.R_rect @ cam.R.T).T
        return d[:, :2] / d[:, 2:3] * self.f + c

    def disparity_range(self, depth_min_mm: float, depth_max_mm: float) -> tuple[float, float]:
        """Disparity ``u_left - u_right`` (px) of points between two depths along the rectified axis."""
        shift = self.c_left[0] - self.c_right[0]
        b = self.baseline_mm * self.f
        return b / depth_max_mm + shift, b / depth_min_mm + shift

    def maps(self, side: str):
        """``cv2.remap`` maps (float32) from the rectified image into the original."""
        cam, c = self._side(side)
        K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
        P = np.array([[self.f, 0, c[0]], [0, self.f, c[1]], [0, 0, 1.0]])
        # OpenCV's R: original camera frame → rectified frame
        return cv2.initUndistortRectifyMap(K, cam.dist, self.R_rect @ cam.R.T, P, self.size, cv2.CV_32FC1)

    def resample(self, side: str, image: np.ndarray) -> np.ndarray:
        """The rectified image of ``side`` (bilinear); outside the original frame is 0."""
        mx, my = self.maps(side)
        return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def rectification_rotation(left: Camera, right: Camera) -> np.ndarray:
    """World→rectified rotation: x along the baseline, z the mean viewing direction made orthogonal."""
    x = right.C - left.C
    x = x / np.linalg.norm(x)
    z = left.R[2] + right.R[2]
    z = z - x * (z @ x)
    z = z / np.linalg.norm(z)
    y = np.cross(z, x)
    return np.vstack([x, y, z])


def _border(cam: Camera, n: int = 64) -> np.ndarray:
    w, h = cam.width - 1, cam.height - 1
    t = np.linspace(0, 1, n)
    return np.vstack([np.column_stack([t * w, np.zeros(n)]), np.column_stack([t * w, np.full(n, h)]),
                      np.column_stack([np.zeros(n), t * h]), np.column_stack([np.full(n, w), t * h])])


def rectify_pair(left: Camera, right: Camera, scale: float = 1.0) -> RectifiedPair:
    """The epipolar geometry of ``left`` and ``right`` (calibrated, same world frame).

    ``scale`` multiplies the principal distance (1: the original resolution).
    The rectified size covers the larger of the two resampled frames; the
    principal points are set per image so each frame starts at column 0.
    """
    if np.linalg.norm(right.C - left.C) < 1e-6:
        raise ValueError("the two cameras share a perspective centre: no baseline to rectify")
    R = rectification_rotation(left, right)
    f = scale * 0.25 * (left.fx + left.fy + right.fx + right.fy)
    boxes = []
    for cam in (left, right):
        xy = pixel_to_normalized(cam, _border(cam))
        d = np.column_stack([xy, np.ones(len(xy))]) @ (R @ cam.R.T).T
        if np.any(d[:, 2] <= 0):
            raise ValueError("a camera looks away from the common image plane: the pair cannot be rectified")
        boxes.append(d[:, :2] / d[:, 2:3] * f)
    v0 = min(b[:, 1].min() for b in boxes)
    v1 = max(b[:, 1].max() for b in boxes)
    widths = [b[:, 0].max() - b[:, 0].min() for b in boxes]
    c_left = np.array([-boxes[0][:, 0].min(), -v0])
    c_right = np.array([-boxes[1][:, 0].min(), -v0])
    size = (int(np.ceil(max(widths))) + 1, int(np.ceil(v1 - v0)) + 1)
    return RectifiedPair(left, right, R, float(f), c_left, c_right, size)


def rig_centre(cameras) -> np.ndarray:
    """The point closest to all cameras' optical axes (world, mm): where the rig looks."""
    from .multiview import linear_intersection

    centres = np.array([c.C for c in cameras])
    axes = np.array([c.R[2] for c in cameras])
    return linear_intersection(centres, axes[None], np.ones((1, len(cameras)), bool))[0]


def subject_depth_bounds(pair: RectifiedPair, centre, radius_mm: float) -> tuple[float, float]:
    """Depth range (mm, along the rectified viewing axis) of a subject within ``radius_mm`` of ``centre``."""
    z = pair.R_rect[2]
    depths = [float(z @ (np.asarray(centre) - c.C)) for c in (pair.left, pair.right)]
    return max(min(depths) - radius_mm, 1.0), max(depths) + radius_mm
