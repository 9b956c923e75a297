"""Measurement of ArUco targets: detection, then corners from fitted edges.

OpenCV's detector finds and identifies the markers; its own sub-pixel corner
refinement is biased (it pulls some corners inward by about 0.2 px), so the
corners are measured independently of it: along each outer edge of the
marker's black border, many intensity profiles across the edge locate the edge
to sub-pixel precision (the step's first moment, which blur does not shift);
the edge points are undistorted with the camera's IOPs when they are known,
a straight line is fitted to each edge, and adjacent lines intersect in the
corner, which is then distorted back to image coordinates.
"""

from __future__ import annotations

import cv2
import numpy as np

from .camera import Camera, normalized_to_pixel, pixel_to_normalized
from .imaging import sample_bilinear

__all__ = ["aruco_dictionary", "detect_markers", "refine_corners", "measure_markers"]


def aruco_dictionary(name: str):
    """The OpenCV predefined ArUco dictionary called ``name`` (e.g. ``DICT_4X4_1000``)."""
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise ValueError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def _to_uint8(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return np.clip(image * 255.0, 0, 255).astype(np.uint8)


def detect_markers(image: np.ndarray, dictionary: str):
    """ArUco markers in a grayscale image.

    Returns
    -------
    ids : (M,) int array
    corners : (M, 4, 2) float array, px, in the order top-left, top-right,
        bottom-right, bottom-left of the printed marker (OpenCV's order);
        OpenCV's coarse, unrefined corners.
    """
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    detector = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)
    corners, ids, _ = detector.detectMarkers(_to_uint8(image))
    if ids is None or len(ids) == 0:
        return np.zeros(0, dtype=int), np.zeros((0, 4, 2))
    return ids.ravel().astype(int), np.asarray(corners, dtype=float).reshape(-1, 4, 2)


def _line_fit(points: np.ndarray, weights: np.ndarray):
    """Total-least-squares lines through weighted points (..., n, 2): (normal, offset)."""
    w = weights / np.maximum(weights.sum(axis=-1, keepdims=True), 1e-12)
    mean = np.einsum("...n,...nk->...k", w, points)
    d = points - mean[..., None, :]
    cov = np.einsum("...n,...ni,...nj->...ij", w, d, d)
    _, vecs = np.linalg.eigh(cov)
    normal = vecs[..., :, 0]  # eigenvector of the smallest eigenvalue
    offset = np.einsum("...k,...k->...", normal, mean)
    return normal, offset


def refine_corners(image: np.ndarray, corners: np.ndarray, camera: Camera | None = None,
                   iterations: int = 2, edge_margin: float = 0.15):
    """Corners of markers from lines fitted to their outer edges.

    Parameters
    ----------
    image : (H, W) array
        Grayscale image (uint8, uint16 or float).
    corners : (M, 4, 2) array
        Approximate corners (px), OpenCV's order.
    camera : Camera, optional
        IOPs for undistorting edge points before the line fit; without them
        the lines are fitted in the distorted image (adequate for a first
        calibration pass, where the marker is small against the distortion).
    edge_margin : float
        Fraction of each edge left out at both ends, clear of the corners.

    Returns
    -------
    refined : (M, 4, 2) array of corners (px, distorted image coordinates)
    rms : (M,) RMS distance (px) of the edge points from their lines
    ok : (M,) bool, False where an edge had too little contrast or the corner moved implausibly
    """
    img = image.astype(np.float32)
    current = np.asarray(corners, dtype=float).copy()
    M = len(current)
    if M == 0:
        return current, np.zeros(0), np.zeros(0, dtype=bool)
    ok = np.ones(M, dtype=bool)
    rms = np.zeros(M)
    for _ in range(iterations):
        a = current
        b = np.roll(current, -1, axis=1)  # edge k runs from corner k to corner k+1
        edge = b - a
        length = np.linalg.norm(edge, axis=-1)  # (M, 4)
        side = length.mean(axis=1)
        # profile half-width: inside the black border cell (a sixth of the side)
        half = np.clip(0.1 * side, 1.5, 12.0)
        n_along = int(np.clip(0.7 * np.median(side), 48, 160))  # about one profile per pixel of edge
        t = np.linspace(edge_margin, 1 - edge_margin, n_along)
        n_across = 33
        s_unit = np.linspace(-1.0, 1.0, n_across)
        direction = edge / length[..., None]
        normal = np.stack([-direction[..., 1], direction[..., 0]], axis=-1)
        centre = current.mean(axis=1, keepdims=True)
        outward = np.sign(np.einsum("mkj,mkj->mk", normal, (a + b) / 2 - centre))
        normal = normal * outward[..., None]
        s = half[:, None, None, None] * s_unit  # (M, 1, 1, S)
        base = a[:, :, None, :] + t[None, None, :, None] * edge[:, :, None, :]  # (M, 4, n, 2)
        pts = base[..., None, :] + s[..., None] * normal[:, :, None, None, :]  # (M, 4, n, S, 2)
        prof = sample_bilinear(img, pts[..., 0], pts[..., 1], border="replicate").astype(float)
        q = max(2, n_across // 6)
        lo = prof[..., :q].mean(axis=-1)  # the black border, inside
        hi = prof[..., -q:].mean(axis=-1)  # the white margin, outside
        contrast = hi - lo
        norm = np.clip((prof - lo[..., None]) / np.where(np.abs(contrast) > 1e-6, contrast, 1.0)[..., None], -0.5, 1.5)
        # first moment of the step: for a step at s_e blurred by any symmetric
        # kernel, the integral of the normalized profile over [-h, h] is h - s_e
        ds = 2.0 / (n_across - 1) * half[:, None, None]
        integral = (norm[..., 1:] + norm[..., :-1]).sum(axis=-1) * 0.5 * ds
        s_edge = half[:, None, None] - integral  # (M, 4, n)
        edge_pts = base + s_edge[..., None] * normal[:, :, None, :]
        good = contrast > max(5.0 if img.max() > 2 else 0.02, 0.0)
        typical = np.median(contrast, axis=-1, keepdims=True)
        good &= contrast > 0.5 * typical
        good &= np.abs(s_edge) < 0.8 * half[:, None, None]
        if camera is not None:
            xy = pixel_to_normalized(camera, edge_pts.reshape(-1, 2))
            ideal = np.column_stack([camera.fx * xy[:, 0] + camera.cx, camera.fy * xy[:, 1] + camera.cy])
            edge_pts = ideal.reshape(edge_pts.shape)
        w = good.astype(float)
        for _ in range(2):  # fit, then refit without outlying edge points
            nrm, off = _line_fit(edge_pts, w)
            resid = np.einsum("mknj,mkj->mkn", edge_pts, nrm) - off[..., None]
            sigma = np.sqrt((w * resid ** 2).sum(-1) / np.maximum(w.sum(-1), 1))
            w = (good & (np.abs(resid) < 3.0 * np.maximum(sigma[..., None], 0.02))).astype(float)
        rms = np.sqrt((w * resid ** 2).sum(axis=(1, 2)) / np.maximum(w.sum(axis=(1, 2)), 1))
        # corner k is where edge k-1 (into it) meets edge k (out of it)
        lines = np.concatenate([nrm, -off[..., None]], axis=-1)  # (M, 4, 3) homogeneous
        X = np.cross(np.roll(lines, 1, axis=1), lines)
        valid = np.abs(X[..., 2]) > 1e-12
        corner = X[..., :2] / np.where(valid, X[..., 2], 1.0)[..., None]
        if camera is not None:
            xy = np.column_stack([(corner[..., 0].ravel() - camera.cx) / camera.fx,
                                  (corner[..., 1].ravel() - camera.cy) / camera.fy])
            corner = normalized_to_pixel(camera, xy).reshape(M, 4, 2)
        enough = (w.sum(axis=-1) >= 6).all(axis=1)
        moved = np.linalg.norm(corner - corners, axis=-1).max(axis=1)
        ok = valid.all(axis=1) & enough & (moved < np.maximum(3.0, 0.1 * side))
        current = np.where(ok[:, None, None], corner, current)
    return current, rms, ok


def measure_markers(image: np.ndarray, dictionary: str, camera: Camera | None = None):
    """Detect markers and measure their corners from fitted edges.

    Returns ``ids (M,)``, ``corners (M, 4, 2)`` px, ``rms (M,)`` px, for the
    markers whose edges could be measured.
    """
    ids, coarse = detect_markers(image, dictionary)
    refined, rms, ok = refine_corners(image, coarse, camera)
    return ids[ok], refined[ok], rms[ok]
