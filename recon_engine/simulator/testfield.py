"""The simulated test field: an octagonal tower carrying ArUco markers.

Every face is a flat white board with a grid of printed markers; its geometry
and the markers' cells are known exactly, so the renderer samples the printed
albedo analytically (sharp edges, no texture resampling) and supersampling
does the anti-aliasing.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..formats import TestField
from .config import TestFieldConfig
from .rig import rotation_about

WHITE = 0.85  # paper albedo
BLACK = 0.04  # printed ink


@dataclass(frozen=True)
class Tower:
    """Geometry of the tower in its own frame (mm), Z up, standing on Z = 0."""

    vertices: np.ndarray  # (N, 3)
    triangles: np.ndarray  # (M, 3); side face f is triangles 2f and 2f + 1
    n_faces: int
    origin: np.ndarray  # (F, 3) lower-left corner of each side face, seen from outside
    u: np.ndarray  # (F, 3) unit vector to the right along the face, seen from outside
    v: np.ndarray  # (F, 3) unit vector up (+Z)
    slots: np.ndarray  # (F, rows, cols) marker id in each slot
    slot_xy: np.ndarray  # (rows, cols, 2) lower-left corner of each slot in face (u, v) mm
    marker_mm: float
    bits: np.ndarray  # (max_id + 1, 6, 6) uint8 printed cells, 1 = white, row 0 at the top
    corners: dict  # marker id -> (4, 3) true corners TL, TR, BR, BL (tower frame)


def make_tower(cfg: TestFieldConfig, rng: np.random.Generator) -> Tower:
    n = cfg.sides
    Rc = cfg.circumradius_mm
    face_w = 2 * Rc * np.sin(np.pi / n)
    need_w = cfg.columns * cfg.marker_mm + (cfg.columns + 1) * cfg.gap_mm
    if need_w > face_w + 1e-6:
        raise ValueError(f"test field: {cfg.columns} markers of {cfg.marker_mm} mm do not fit a face of {face_w:.0f} mm")
    height = cfg.rows * cfg.marker_mm + (cfg.rows + 1) * cfg.gap_mm
    z0 = cfg.bottom_mm - cfg.gap_mm
    angles = 2 * np.pi * (np.arange(n) + 0.5) / n
    ring = np.column_stack([Rc * np.cos(angles), Rc * np.sin(angles)])
    verts, tris, origin, u, v = [], [], [], [], []
    for f in range(n):
        a, b = ring[f], ring[(f + 1) % n]  # counter-clockwise seen from above
        # seen from outside, counter-clockwise is to the right: a is left, b right
        base = len(verts)
        verts += [[*a, z0], [*b, z0], [*b, z0 + height], [*a, z0 + height]]
        tris += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        origin.append([*a, z0])
        uu = np.array([*(b - a), 0.0])
        u.append(uu / np.linalg.norm(uu))
        v.append([0.0, 0.0, 1.0])
    # caps (no markers) close the tower and its stand
    base = len(verts)
    verts += [[*p, z0 + height] for p in ring] + [[0, 0, z0 + height]]
    tris += [[base + n, base + f, base + (f + 1) % n] for f in range(n)]
    base = len(verts)
    verts += [[*p, 0.0] for p in ring * 0.25] + [[*p, z0] for p in ring * 0.25]
    for f in range(n):  # a slim stand down to the floor
        g = (f + 1) % n
        tris += [[base + f, base + g, base + n + g], [base + f, base + n + g, base + n + f]]
    base2 = len(verts)
    verts += [[*p, z0] for p in ring] + [[0, 0, z0]]
    tris += [[base2 + n, base2 + (f + 1) % n, base2 + f] for f in range(n)]
    origin, u, v = np.array(origin), np.array(u), np.array(v)

    # markers: ids shuffled over the slots, drawn from the dictionary
    n_markers = n * cfg.rows * cfg.columns
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, cfg.aruco_dictionary))
    n_dict = dictionary.bytesList.shape[0]
    ids = np.sort(rng.choice(n_dict, n_markers, replace=False))
    slots = rng.permutation(ids).reshape(n, cfg.rows, cfg.columns)
    x0 = (face_w - need_w) / 2 + cfg.gap_mm
    slot_xy = np.zeros((cfg.rows, cfg.columns, 2))
    for r in range(cfg.rows):
        for c in range(cfg.columns):
            slot_xy[r, c] = [x0 + c * (cfg.marker_mm + cfg.gap_mm), cfg.gap_mm + r * (cfg.marker_mm + cfg.gap_mm)]
    bits = np.ones((ids.max() + 1, 6, 6), dtype=np.uint8)
    for mid in ids:
        img = cv2.aruco.generateImageMarker(dictionary, int(mid), 6, borderBits=1)
        bits[mid] = (img > 127).astype(np.uint8)
    corners = {}
    m = cfg.marker_mm
    for f in range(n):
        for r in range(cfg.rows):
            for c in range(cfg.columns):
                x, y = slot_xy[r, c]
                local = np.array([[x, y + m], [x + m, y + m], [x + m, y], [x, y]])  # TL, TR, BR, BL
                corners[int(slots[f, r, c])] = origin[f] + local[:, :1] * u[f] + local[:, 1:] * v[f]
    return Tower(np.asarray(verts, float), np.asarray(tris, np.int32), n, origin, u, v,
                 slots, slot_xy, m, bits, corners)


def tower_albedo(tower: Tower, face: np.ndarray, P_tower: np.ndarray) -> np.ndarray:
    """Printed albedo at points ``P_tower`` (N, 3, tower frame) on side faces ``face`` (N,)."""
    rel = (P_tower - tower.origin[face]).astype(np.float32)
    x = (rel * tower.u[face].astype(np.float32)).sum(axis=1)
    y = rel[:, 2]  # faces are vertical: v is +Z
    rows, cols = tower.slots.shape[1:]
    m = tower.marker_mm
    x0, y0 = tower.slot_xy[0, 0]
    pitch_x = tower.slot_xy[0, 1, 0] - x0 if cols > 1 else 2 * m
    pitch_y = tower.slot_xy[1, 0, 1] - y0 if rows > 1 else 2 * m
    # slot, and position inside the slot in units of marker cells (6 per side)
    gx = (x - x0) / pitch_x
    gy = (y - y0) / pitch_y
    c = np.floor(gx).astype(np.int32)
    r = np.floor(gy).astype(np.int32)
    lx = (gx - c) * (pitch_x / m * 6)
    ly = (gy - r) * (pitch_y / m * 6)
    inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols) & (lx < 6) & (ly < 6)
    np.clip(r, 0, rows - 1, out=r)
    np.clip(c, 0, cols - 1, out=c)
    cell_c = np.minimum(lx.astype(np.int32), 5)
    cell_r = 5 - np.minimum(ly.astype(np.int32), 5)  # row 0 at the top
    white = tower.bits[tower.slots[face, r, c], cell_r, cell_c].astype(bool)
    return np.where(inside & ~white, BLACK, WHITE)


def draw_poses(cfg: TestFieldConfig, rng: np.random.Generator) -> list:
    """Rigid poses (R, t) of the tower in the world, ``X_world = R @ X_tower + t``.

    Pose 0 is the identity: the calibration frame is the tower's frame at pose 0.
    Later poses turn the tower about the vertical, shift, lift and tilt it.
    """
    poses = [(np.eye(3), np.zeros(3))]
    for k in range(1, cfg.poses):
        yaw = k * cfg.pose_yaw_deg + rng.uniform(-3, 3)
        axis = np.array([*rng.normal(0, 1, 2), 0.0])
        R = rotation_about(axis, rng.uniform(-cfg.pose_tilt_deg, cfg.pose_tilt_deg)) @ rotation_about([0, 0, 1], yaw)
        t = np.array([*rng.uniform(-cfg.pose_shift_mm, cfg.pose_shift_mm, 2), rng.uniform(0, cfg.pose_lift_mm)])
        poses.append((R, t))
    return poses


def surveyed(tower: Tower, cfg: TestFieldConfig, rng: np.random.Generator) -> TestField:
    """The test field as surveyed: true corners plus survey noise of ``sigma_mm``."""
    markers = {mid: c + rng.normal(0, cfg.sigma_mm, c.shape) for mid, c in sorted(tower.corners.items())}
    return TestField(cfg.name, cfg.aruco_dictionary, markers, cfg.sigma_mm)
