"""The patient's frame: vertical from the rig, facing direction and mid-sagittal plane from the shape.

Patient frame (mm): x towards the patient's left, y posterior (out of the
back), z up (the rig's +Z, as the test field stands); right-handed. For the
simulator's subject standing at rest it coincides with the world frame.
Reported lateral values are turned to the clinical sign: positive towards the
patient's right, i.e. ``-x``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import RigidConfig
from .rigid import register_rigid
from .torso import PlaneIndex, Torso

_AXES = {"+x": (1, 0), "-x": (-1, 0), "+y": (0, 1), "-y": (0, -1)}


@dataclass
class PatientFrame:
    """``p_patient = R @ (p_rig - origin)``; rows of ``R``: left, posterior, up (unit, rig frame)."""

    R: np.ndarray
    origin: np.ndarray

    def to_patient(self, p):
        return (np.asarray(p, float) - self.origin) @ self.R.T

    def to_rig(self, q):
        return np.asarray(q, float) @ self.R + self.origin

    def rotate(self, n):
        return np.asarray(n, float) @ self.R.T

    def to_dict(self):
        return {"origin_mm": self.origin.tolist(), "left": self.R[0].tolist(), "posterior": self.R[1].tolist(),
                "up": self.R[2].tolist()}


def frame_from_posterior(posterior, origin) -> PatientFrame:
    """The frame whose y is the horizontal part of ``posterior`` and z the rig's +Z."""
    z = np.array([0.0, 0.0, 1.0])
    y = np.array([posterior[0], posterior[1], 0.0])
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return PatientFrame(np.vstack([x, y, z]), np.asarray(origin, float))


def width_axis(points: np.ndarray) -> np.ndarray:
    """Horizontal unit vector of the trunk's largest horizontal spread (the left-right axis, sign arbitrary)."""
    z0, z1 = np.percentile(points[:, 2], [20, 80])
    p = points[(points[:, 2] >= z0) & (points[:, 2] <= z1), :2]
    p = p - np.median(p, axis=0)
    _, vec = np.linalg.eigh(p.T @ p)
    return np.array([vec[0, 1], vec[1, 1], 0.0])


def facing_score(points: np.ndarray, direction: np.ndarray, half_width_mm: float = 30.0) -> float:
    """How convex (mm) the midline profile is on the side ``direction`` points to.

    Along the trunk's vertical midline, the outermost extent in ``direction`` at
    every height; the score is the mean extent of the middle 40 % of the heights
    minus the chord between the lowest and highest 15 %. The back is concave
    there (lumbar lordosis between sacrum and thoracic kyphosis: negative score),
    the front convex (abdomen and chest: positive).
    """
    d = np.asarray(direction, float)
    across = np.cross([0.0, 0.0, 1.0], d)
    c = np.median(points[:, :2], axis=0)
    rel = points[:, :2] - c
    a = rel @ across[:2]
    e = rel @ d[:2]
    mid = np.abs(a) < half_width_mm
    z = points[mid, 2]
    ext = e[mid]
    lo, hi = np.percentile(points[:, 2], [2, 98])
    edges = np.linspace(lo, hi, 41)
    prof = []
    for k in range(40):
        sel = (z >= edges[k]) & (z < edges[k + 1])
        prof.append(np.max(ext[sel]) if sel.sum() >= 3 else np.nan)
    prof = np.asarray(prof)
    if np.isnan(prof).sum() > 20:
        return 0.0
    ends = np.nanmean(prof[:6]), np.nanmean(prof[-6:])
    middle = np.nanmean(prof[12:28])
    return float(middle - 0.5 * (ends[0] + ends[1]))


def detect_posterior(points: np.ndarray, facing: str | None = None) -> tuple[np.ndarray, dict]:
    """Posterior unit vector (horizontal, rig frame) and how it was found.

    ``facing``: "+x", "-x", "+y" or "-y" forces the posterior direction (the
    rig frame axis the back faces); otherwise the depth axis (perpendicular to
    the widest horizontal spread) is taken, its sign from :func:`facing_score`.
    """
    if facing is not None:
        if facing not in _AXES:
            raise ValueError(f"facing {facing!r}: choose one of {sorted(_AXES)}")
        v = np.array([*_AXES[facing], 0.0], float)
        return v, {"method": "given", "facing": facing}
    w = width_axis(points)
    depth = np.cross([0.0, 0.0, 1.0], w)
    s_plus, s_minus = facing_score(points, depth), facing_score(points, -depth)
    post = depth if s_plus < s_minus else -depth
    return post, {"method": "detected", "score_mm": {"back": float(min(s_plus, s_minus)),
                                                     "front": float(max(s_plus, s_minus))}}


def mirror(torso: Torso, frame: PatientFrame) -> Torso:
    """The torso reflected about the frame's mid-sagittal plane (x = 0)."""
    H = frame.R.T @ np.diag([-1.0, 1.0, 1.0]) @ frame.R
    p = (torso.points - frame.origin) @ H.T + frame.origin
    return Torso(p, torso.normals @ H.T, {}, torso.source)


def symmetry_plane(torso: Torso, frame: PatientFrame, cfg: RigidConfig | None = None, mask=None,
                   index: PlaneIndex | None = None) -> dict:
    """Register the torso's mirror image to itself; the mid-sagittal plane and the asymmetry map.

    Returns ``{"frame": PatientFrame (x along the plane's normal, origin on the plane),
    "R", "t" (mirror image -> torso), "distance_mm" (N,) signed normal distance of each
    mirrored point to the torso (NaN off the surface), "over" (N,) bool}``.
    """
    cfg = cfg or RigidConfig(initial_distance_mm=60.0, min_distance_mm=3.0)
    m = mirror(torso, frame)
    index = index or PlaneIndex(torso)
    res = register_rigid(m, torso, cfg, initial=(np.eye(3), np.zeros(3)), fixed_index=index, weights_mask=mask)
    H = frame.R.T @ np.diag([-1.0, 1.0, 1.0]) @ frame.R
    A = res["R"] @ H
    vals, vecs = np.linalg.eigh(0.5 * (A + A.T))
    n = vecs[:, 0]
    n[2] = 0.0
    n /= np.linalg.norm(n)
    if n @ frame.R[0] < 0:
        n = -n
    # a point on the plane: midway between a point and its image
    x = torso.points if mask is None else torso.points[mask]
    img = ((x - frame.origin) @ H.T + frame.origin) @ res["R"].T + res["t"]
    origin = 0.5 * (x + img).mean(axis=0)
    post = np.cross([0.0, 0.0, 1.0], n)
    new = frame_from_posterior(post, origin)
    xm = m.points @ res["R"].T + res["t"]
    d, _, _, over = index.distances(xm, cfg.max_tangential)
    d = np.where(over, d, np.nan)
    return {"frame": new, "R": res["R"], "t": res["t"], "distance_mm": d, "over": over, "registration": res}
