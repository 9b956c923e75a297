"""The simulated rig: cameras with their own lenses, projectors, arm swings.

World frame: right-handed, mm, Z up, origin on the floor at the rig centre
(the test field's pose 0 frame). The patient stands at the centre facing -Y.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..camera import Camera
from ..formats import Arm, CameraSpec, Rig
from ..pattern import make_pattern
from .config import ScenarioConfig
from .lens import Lens

LENS_STREAM = 29  # seed-sequence key of the lens terms' random stream


def look_at(C, target, up=(0.0, 0.0, 1.0), roll_deg: float = 0.0) -> np.ndarray:
    """World→camera rotation (OpenCV frame) of a camera at ``C`` looking at ``target``."""
    z = np.asarray(target, float) - np.asarray(C, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.vstack([x, y, z])
    a = np.radians(roll_deg)
    roll = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return roll @ R


def rotation_about(axis, angle_deg: float) -> np.ndarray:
    """Active rotation matrix about a unit ``axis`` by ``angle_deg`` (right hand)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(angle_deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


@dataclass(frozen=True)
class Projector:
    """A pattern projector modelled as an inverse pinhole camera (projector px)."""

    id: str
    arm: str
    model: Camera  # world→projector orientation and its pinhole (no distortion)
    pattern: np.ndarray  # (height, width) float32 in [0, 1]


@dataclass(frozen=True)
class RigTruth:
    rig: Rig
    cameras: dict  # camera id -> Camera, as calibrated (world = test field pose 0)
    projectors: dict  # arm id -> Projector
    pivots: dict  # arm id -> (3,) pivot of the arm's swing (mm)
    lenses: dict = None  # camera id -> lens.Lens, the true lens the renderer traces (cameras hold its engine terms)


def make_rig(cfg: ScenarioConfig, rng: np.random.Generator, centre_height_mm: float,
             rng_lens: np.random.Generator | None = None) -> RigTruth:
    """Cameras and projectors of the rig at calibration time.

    Each camera has its own true lens (:class:`lens.Lens`: focal lengths in x
    and y, principal point, radial, decentring and thin-prism distortion)
    drawn from ``cfg.camera``; cameras stand on an arc around the rig centre,
    aimed at the torso centre with mounting scatter. ``rng_lens`` draws the
    lens terms beyond the old simulator's (default: a stream of its own from
    ``cfg.seed``).
    """
    cc, rc, pc = cfg.camera, cfg.rig, cfg.projector
    if rng_lens is None:
        rng_lens = np.random.default_rng(np.random.SeedSequence([cfg.seed, LENS_STREAM]))
    arms, specs, cameras, projectors, pivots, lenses = [], {}, {}, {}, {}, {}
    step = np.degrees(rc.camera_spacing_mm / rc.camera_radius_mm)
    centre = np.array([0.0, 0.0, centre_height_mm])
    for k, arm_id in enumerate(rc.arms):
        azimuth = rc.first_arm_azimuth_deg + 360.0 * k / len(rc.arms)
        ids = [f"{arm_id}{j + 1}" for j in range(rc.cameras_per_arm)]
        positions = []
        for j, cam_id in enumerate(ids):
            # cameras run counter-clockwise along the arm, seen from above
            az = np.radians(azimuth + (j - (rc.cameras_per_arm - 1) / 2) * step)
            C = np.array([rc.camera_radius_mm * np.cos(az), rc.camera_radius_mm * np.sin(az),
                          centre_height_mm + rng.normal(0, rc.camera_height_sigma_mm)])
            aim = centre + rng.normal(0, rc.aim_sigma_mm, 3)
            R = look_at(C, aim, roll_deg=rng.normal(0, rc.roll_sigma_deg))
            f_px = cc.focal_mm * (1 + rng.normal(0, cc.focal_spread)) / cc.pixel_size_mm
            k1, k2 = rng.uniform(*cc.k1_range), rng.normal(0, cc.k2_sigma)
            p1, p2 = rng.normal(0, cc.p_sigma), rng.normal(0, cc.p_sigma)
            fy = f_px * (1 + rng.normal(0, 1e-4))
            cx = (cc.width - 1) / 2 + rng.normal(0, cc.principal_point_sigma_px)
            cy = (cc.height - 1) / 2 + rng.normal(0, cc.principal_point_sigma_px)
            # the terms beyond the old lens come from their own stream (the draws above are the old ones)
            e = rng_lens.normal(0, 1, 8)
            lens = Lens(f_px, fy * (1 + cc.aspect_sigma * e[0]), cx, cy, k1=k1, k2=k2, k3=cc.k3_sigma * e[1],
                        p1=p1, p2=p2, p3=cc.p3_sigma * e[2], s1=cc.prism_sigma * e[3], s2=cc.prism2_sigma * e[4],
                        s3=cc.prism_sigma * e[5], s4=cc.prism2_sigma * e[6], skew=cc.skew_sigma * e[7])
            lenses[cam_id] = lens
            cameras[cam_id] = engine_camera(lens, cc.width, cc.height, R, C)
            specs[cam_id] = CameraSpec(cam_id, cc.width, cc.height, cc.pixel_size_mm, cc.focal_mm,
                                       "simulated low-cost camera")
            positions.append(C)
        pivots[arm_id] = np.mean(positions, axis=0)
        az = np.radians(azimuth)
        P = np.array([pc.distance_mm * np.cos(az), pc.distance_mm * np.sin(az),
                      centre_height_mm + pc.height_offset_mm])
        f_proj = (pc.width / 2) / (pc.coverage_mm / 2 / pc.distance_mm)
        model = Camera(pc.width, pc.height, f_proj, f_proj, (pc.width - 1) / 2, (pc.height - 1) / 2,
                       np.zeros(5), look_at(P, centre), P)
        pattern, _, _ = make_pattern(pc.width, pc.height, seed=cfg.seed * 100 + k)
        projectors[arm_id] = Projector(f"P{arm_id}", arm_id, model, pattern)
        arms.append(Arm(arm_id, tuple(ids), f"P{arm_id}"))
    # the footplate: the patient stands facing -Y, back towards +Y (azimuth 90 deg); the rig names the arms
    # within 50 deg of that (arms A and B of the default layout)
    azimuths = {a.id: rc.first_arm_azimuth_deg + 360.0 * k / len(rc.arms) for k, a in enumerate(arms)}
    back = tuple(a for a, az in azimuths.items() if abs((az - 90.0 + 180.0) % 360.0 - 180.0) <= 50.0)
    rig = Rig(rc.serial, tuple(arms), specs, back)
    return RigTruth(rig, cameras, projectors, pivots, lenses)


def engine_camera(lens: Lens, width: int, height: int, R, C) -> Camera:
    """The engine's view of a true lens: its terms the engine models (the others are left out)."""
    return Camera(width, height, lens.fx, lens.fy, lens.cx, lens.cy, lens.dist5, R, C)


def apply_lens_changes(truth: RigTruth, changes) -> RigTruth:
    """The rig with some lenses disturbed since installation.

    ``changes``: (camera id, what, amount) with what ``"pd"`` (relative change
    of the principal distance), ``"pp_x"`` / ``"pp_y"`` (principal point shift,
    px) or ``"k1"`` (added to k1).
    """
    if not changes:
        return truth
    cameras, lenses = dict(truth.cameras), dict(truth.lenses)
    for cam_id, what, amount in changes:
        if cam_id not in cameras:
            raise ValueError(f"lens change for unknown camera {cam_id!r}")
        c = lenses[cam_id]
        if what == "pd":
            c = replace(c, fx=c.fx * (1 + amount), fy=c.fy * (1 + amount))
        elif what == "pp_x":
            c = replace(c, cx=c.cx + amount)
        elif what == "pp_y":
            c = replace(c, cy=c.cy + amount)
        elif what == "k1":
            c = replace(c, k1=c.k1 + amount)
        else:
            raise ValueError(f"unknown lens change {what!r}: use pd, pp_x, pp_y or k1")
        lenses[cam_id] = c
        cam = cameras[cam_id]
        cameras[cam_id] = engine_camera(c, cam.width, cam.height, cam.R, cam.C)
    return replace(truth, cameras=cameras, lenses=lenses)


def draw_arm_displacements(cfg: ScenarioConfig, rng: np.random.Generator, truth: RigTruth) -> dict:
    """Rigid displacement of every arm at one torso capture.

    The reference (first) arm stays; every other arm turns about the vertical
    through its pivot by up to ``arm_rotation_max_deg``, tilts a little and
    shifts by a few mm. Returns arm id -> dict(R, t, yaw_deg) with the
    displacement ``X' = R @ X + t`` in the world frame (mm).
    """
    rc = cfg.rig
    out = {}
    for k, arm in enumerate(truth.rig.arms):
        if k == 0:
            out[arm.id] = {"R": np.eye(3), "t": np.zeros(3), "yaw_deg": 0.0}
            continue
        yaw = rng.uniform(-rc.arm_rotation_max_deg, rc.arm_rotation_max_deg)
        tilt_axis = np.array([*rng.normal(0, 1, 2), 0.0])
        tilt = rng.uniform(-rc.arm_tilt_max_deg, rc.arm_tilt_max_deg)
        R = rotation_about(tilt_axis, tilt) @ rotation_about([0, 0, 1], yaw)
        shift = rng.uniform(-rc.arm_translation_max_mm, rc.arm_translation_max_mm, 3)
        p = truth.pivots[arm.id]
        out[arm.id] = {"R": R, "t": p - R @ p + shift, "yaw_deg": yaw}
    return out


def displace(truth: RigTruth, displacements: dict) -> tuple[dict, dict]:
    """Cameras and projectors after the arms moved by ``displacements``."""
    cameras, projectors = {}, {}
    for arm in truth.rig.arms:
        D = displacements[arm.id]
        for cam_id in arm.cameras:
            cam = truth.cameras[cam_id]
            cameras[cam_id] = cam.with_pose(cam.R @ D["R"].T, D["R"] @ cam.C + D["t"])
        proj = truth.projectors[arm.id]
        m = proj.model
        projectors[arm.id] = Projector(proj.id, proj.arm, m.with_pose(m.R @ D["R"].T, D["R"] @ m.C + D["t"]),
                                       proj.pattern)
    return cameras, projectors
