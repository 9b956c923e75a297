"""Subjects for the simulator: realistic anatomy, scoliotic deformation, sway.

Two bodies: the CC0 MakeHuman hm08 base mesh (whole body, scaled to an
adolescent, smoothed by Loop subdivision) and a parametric torso of
superelliptic sections. Both stand at the rig centre, feet on the floor
(world Z = 0), facing -Y (their back towards +Y); the patient's left is +X.

A scoliotic curve is applied along the spine line: lateral deviation and
axial rotation of each horizontal section about the spine, plus a rib
prominence on the convex side. Sign convention of the truth: lateral
deviation positive towards the patient's right (-X); axial rotation positive
when the vertebral bodies turn their front towards the patient's right, which
pushes the right back posteriorly (a right rib hump).
"""

from __future__ import annotations

import functools
import gzip
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..bundle import rodrigues
from .config import SubjectConfig

# Shipped with the package (CC0, gzip-compressed): a fresh clone needs nothing beside it.
DEFAULT_MESH = Path(__file__).resolve().parent / "data" / "makehuman-hm08-base.obj.gz"


@dataclass(frozen=True)
class Body:
    """A subject at rest (no curve, no sway), in the world frame (mm)."""

    name: str
    vertices: np.ndarray  # (N, 3)
    triangles: np.ndarray  # (M, 3) int
    torso_faces: np.ndarray  # (M,) bool: the torso that the scanner must measure
    spine: np.ndarray  # (K, 3) spine line from sacrum to C7, increasing Z
    z_sacrum: float
    z_c7: float
    # (2, 4, 3) the left and right arms' shoulder, elbow, wrist and middle fingertip joints (MakeHuman only)
    arm_joints: np.ndarray | None = None
    dimples: np.ndarray | None = None  # (2, 3) bottoms of the left (+X) and right lumbar dimples, on the skin


def mesh_path() -> Path:
    """Where the MakeHuman mesh lives: ``TORSOSCAN_MAKEHUMAN_OBJ`` or the copy shipped in the package."""
    import os

    env = os.environ.get("TORSOSCAN_MAKEHUMAN_OBJ")
    return Path(env) if env else DEFAULT_MESH


def _read_obj_groups(path: Path):
    vertices, faces, cur = [], {}, None
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rt", encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("v "):
                vertices.append(line.split()[1:4])
            elif line.startswith("g "):
                cur = line.split()[1]
            elif line.startswith("f "):
                faces.setdefault(cur, []).append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
    return np.asarray(vertices, dtype=float), faces


def _segment_distance(P, a, b):
    ab = b - a
    t = np.clip(((P - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1)


@functools.lru_cache(maxsize=4)
def load_makehuman(stature_mm: float = 1550.0, subdivisions: int = 2, path: str | None = None) -> Body:
    """The MakeHuman body scaled to ``stature_mm``, Loop-subdivided ``subdivisions`` times."""
    from ..o3d import o3d

    src = Path(path) if path else mesh_path()
    if not src.exists():
        raise FileNotFoundError(f"{src}: the MakeHuman mesh is missing (set TORSOSCAN_MAKEHUMAN_OBJ)")
    V, groups = _read_obj_groups(src)
    if "body" not in groups:
        raise ValueError(f"{src}: no group 'body'")
    quads = np.asarray([f for f in groups["body"] if len(f) == 4])
    tris = [np.asarray([f for f in groups["body"] if len(f) == 3], dtype=int).reshape(-1, 3)]
    tris = np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]], *tris])
    used = np.unique(tris)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))

    def joint(name):
        idx = np.unique(np.concatenate([np.asarray(f) for f in groups[f"joint-{name}"]]))
        return V[idx].mean(axis=0)

    # mesh: x = body's left, y up, z front  ->  world: X left, Y back, Z up
    to_world = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    body_v = V[used]
    floor = body_v[:, 1].min()
    scale = stature_mm / (body_v[:, 1].max() - floor)

    def world(p):
        p = np.atleast_2d(p) - [0.0, floor, 0.0]
        return (p @ to_world.T) * scale

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(world(body_v)),
                                     o3d.utility.Vector3iVector(remap[tris]))
    if subdivisions:
        mesh = mesh.subdivide_loop(subdivisions)
    vertices = np.asarray(mesh.vertices).copy()
    triangles = np.asarray(mesh.triangles).copy()

    spine_names = ["pelvis", "spine-4", "spine-3", "spine-2", "spine-1", "neck"]
    spine = world(np.array([joint(n) for n in spine_names]))
    spine[:, 0] = 0.0  # the mesh is symmetric; keep the spine in the mid-sagittal plane
    z_sac, z_c7 = spine[0, 2], spine[-1, 2]

    # the torso: between the sacral point and C7, arms excluded
    centroids = vertices[triangles].mean(axis=1)
    arm = np.zeros(len(centroids), dtype=bool)
    for side in ("l", "r"):
        s, e, h = (world(joint(f"{side}-{n}"))[0] for n in ("shoulder", "elbow", "hand"))
        radius = 0.62 * scale  # upper-arm radius with margin (mesh units)
        arm |= _segment_distance(centroids, s, e) < radius
        arm |= _segment_distance(centroids, e, h) < radius
        arm |= np.abs(centroids[:, 0]) > abs(s[0]) + 0.1 * scale
    torso = (centroids[:, 2] > z_sac - 30.0) & (centroids[:, 2] < z_c7) & ~arm
    arm_joints = np.stack([np.vstack([world(joint(f"{side}-{n}")) for n in ("shoulder", "elbow", "hand", "finger-3-4")])
                           for side in ("l", "r")])
    return Body("makehuman", vertices, triangles, torso, spine, float(z_sac), float(z_c7), arm_joints)


def make_parametric(stature_mm: float = 1550.0, n_around: int = 360, n_up: int = 260) -> Body:
    """A closed parametric torso: superelliptic sections, spinal furrow, scapulae."""
    k = stature_mm / 1550.0
    z_sac, z_c7 = 828.0 * k, 1308.0 * k
    z0, z1 = z_sac - 90.0 * k, z_c7 + 70.0 * k
    z = np.linspace(z0, z1, n_up)
    s = (z - z_sac) / (z_c7 - z_sac)
    # half-width and half-depths (mm) against the spine level s, smooth in s
    knots = np.array([-0.2, 0.0, 0.35, 0.7, 0.92, 1.02, 1.2])
    half_w = np.interp(s, knots, [168, 160, 122, 138, 165, 90, 55]) * k
    back_d = np.interp(s, knots, [92, 88, 70, 82, 78, 60, 45]) * k
    front_d = np.interp(s, knots, [95, 90, 88, 102, 92, 60, 45]) * k
    t = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    c, sn = np.cos(t), np.sin(t)
    e = 2.0 / 2.6  # superellipse exponent 2.6: squarer than an ellipse
    x = half_w[:, None] * np.sign(c) * np.abs(c) ** e
    depth = np.where(sn[None, :] > 0, back_d[:, None], front_d[:, None])
    y = depth * np.sign(sn) * np.abs(sn) ** e
    # spinal furrow and scapulae on the back (+Y)
    back = np.clip(sn, 0, None)[None, :] ** 2
    furrow = 4.0 * k * np.exp(-0.5 * (x / (14.0 * k)) ** 2) * back * np.clip((s[:, None] - 0.05) / 0.2, 0, 1)
    scap = sum(6.0 * k * np.exp(-0.5 * (((x - sx * k) / (35 * k)) ** 2 + ((s[:, None] - 0.8) / 0.09) ** 2))
               for sx in (-80.0, 80.0)) * back
    y = y - furrow + scap
    grid = np.stack([x, y, np.broadcast_to(z[:, None], x.shape)], axis=-1)
    vertices = grid.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_up - 1), np.arange(n_around), indexing="ij")
    a = i * n_around + j
    b = i * n_around + (j + 1) % n_around
    c_, d = a + n_around, b + n_around
    quads = np.stack([a, b, d, c_], axis=-1).reshape(-1, 4)
    # outward normals: vertices go counter-clockwise seen from above, z grows
    tris = np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    # caps
    bottom = len(vertices)
    top = bottom + 1
    vertices = np.vstack([vertices, [0, 0, z0], [0, 0, z1]])
    ring0 = np.arange(n_around)
    ring1 = (n_up - 1) * n_around + ring0
    caps = np.vstack([
        np.column_stack([np.full(n_around, bottom), (ring0 + 1) % n_around, ring0]),
        np.column_stack([np.full(n_around, top), ring1, (ring1 - ring1[0] + 1) % n_around + ring1[0]]),
    ])
    triangles = np.vstack([tris, caps])
    centroids = vertices[triangles].mean(axis=1)
    torso = (centroids[:, 2] > z_sac - 30.0 * k) & (centroids[:, 2] < z_c7)
    torso[len(tris):] = False
    spine_z = np.linspace(z_sac, z_c7, 6)
    spine = np.column_stack([np.zeros(6), np.interp(spine_z, z, back_d) - 55.0 * k, spine_z])
    return Body("parametric", vertices, triangles, torso, spine, float(z_sac), float(z_c7))


def load_body(cfg: SubjectConfig) -> Body:
    """The subject at rest: the chosen torso at ``cfg.stature_mm``, shaped by the build (:func:`shape_body`)."""
    if cfg.torso == "makehuman":
        body = load_makehuman(cfg.stature_mm)
    elif cfg.torso == "parametric":
        body = make_parametric(cfg.stature_mm)
    else:
        raise ValueError(f"unknown torso {cfg.torso!r}: choose 'makehuman' or 'parametric'")
    return shape_body(body, cfg)


def shape_body(body: Body, cfg: SubjectConfig) -> Body:
    """The body in another build: widths and depths about the spine line, belly, breasts, hips, arms, hair.

    Every change keeps the spine line (x = 0 and its depth) where it is, so
    the truth (spine, landmarks behind C7 and the sacrum) follows the skin.
    Lengths in mm, world frame (the subject faces -Y, left +X).
    """
    defaults = (1.0, 1.0, 0.0, 0.0, 1.0, 0.0, False, 0.0, 0.0, 0.0)
    build = (cfg.build_width, cfg.build_depth, cfg.belly_mm, cfg.breasts_mm, cfg.hips, cfg.arm_abduction_deg,
             cfg.arms_crossed, cfg.neck_hair_mm, cfg.dimples_mm, cfg.pelvic_obliquity_mm)
    if build == defaults:
        return body
    if cfg.arms_crossed and (body.arm_joints is None or cfg.arm_abduction_deg):
        raise ValueError("SubjectConfig.arms_crossed needs the MakeHuman body (torso='makehuman', the parametric "
                         f"torso has no arms; this one is {body.name!r}) and arm_abduction_deg 0 (it is "
                         f"{cfg.arm_abduction_deg})")
    V = body.vertices.copy()
    z = V[:, 2]
    L = body.z_c7 - body.z_sacrum
    s = (z - body.z_sacrum) / L  # spine level: sacrum 0, C7 1
    sy = np.interp(z, body.spine[:, 2], body.spine[:, 1])
    if body.arm_joints is not None and cfg.arm_abduction_deg:
        V = _turn_arms(V, body, cfg.arm_abduction_deg)
    if cfg.arms_crossed:
        V = _cross_arms(V, body)
    front = np.clip(-(V[:, 1] - sy) / 60.0, 0.0, 1.0)  # 0 on the back, 1 on the front
    # the build: widths about the mid-sagittal plane, depths about the spine line
    hips = 1.0 + (cfg.hips - 1.0) * _bump(s, -0.5, -0.05, 0.35)
    V[:, 0] *= cfg.build_width * hips
    V[:, 1] = sy + (V[:, 1] - sy) * cfg.build_depth
    across = V[:, 0] / (120.0 * cfg.build_width)
    if cfg.belly_mm:
        V[:, 1] -= cfg.belly_mm * _bump(s, -0.1, 0.28, 0.62) * np.exp(-0.5 * across ** 2) * front
    if cfg.breasts_mm:
        for side in (-1.0, 1.0):
            d2 = ((V[:, 0] - side * 75.0 * cfg.build_width) / 45.0) ** 2 + ((s - 0.74) / 0.07) ** 2
            V[:, 1] -= cfg.breasts_mm * np.exp(-0.5 * d2) * front
    if cfg.neck_hair_mm:
        # a mass of hair lies on the back of the neck and ends at C7: it hides the skin over the vertebra
        # prominens, as long hair does when not tied up
        back = np.clip((V[:, 1] - sy) / 30.0, 0.0, 1.0) * np.exp(-0.5 * (V[:, 0] / 45.0) ** 2)
        V[:, 1] += cfg.neck_hair_mm * back * np.clip((z - body.z_c7 + 10.0) / 30.0, 0.0, 1.0)
    on_back = np.clip((V[:, 1] - sy) / 30.0, 0.0, 1.0)
    half = cfg.dimple_half_spacing_mm * cfg.build_width * cfg.hips
    centres = np.array([[half, 0.0, body.z_sacrum + cfg.dimple_height_mm],
                        [-half, 0.0, body.z_sacrum + cfg.dimple_height_mm]])
    if cfg.pelvic_obliquity_mm:
        tilt = np.arctan2(cfg.pelvic_obliquity_mm, 2.0 * half)
        reach = cfg.dimple_height_mm + 10.0
        V, centres = _tilt_pelvis(V, body, tilt, reach), _tilt_pelvis(centres, body, tilt, reach)
    if cfg.dimples_mm:
        # a hollow over each posterior superior iliac spine, pressed in along -Y (into the body), 2-3 cm across
        for c in centres:
            d2 = ((V[:, 0] - c[0]) / 11.0) ** 2 + ((V[:, 2] - c[2]) / 14.0) ** 2
            V[:, 1] -= cfg.dimples_mm * np.exp(-0.5 * d2) * on_back
    return replace(body, vertices=V, dimples=_onto_back(V, body.triangles, centres))


def _tilt_pelvis(V: np.ndarray, body: Body, angle: float, whole_below_mm: float = 40.0) -> np.ndarray:
    """The pelvis turned about the sacral point's forward axis by ``angle`` (rad; +: the right side, -X, up),
    whole up to ``whole_below_mm`` above the sacral point (the iliac spines) and fading out over the lumbar
    spine (to 30 % of the trunk up)."""
    L = body.z_c7 - body.z_sacrum
    top = body.z_sacrum + 0.3 * L
    w = np.clip((top - V[:, 2]) / (top - body.z_sacrum - whole_below_mm), 0.0, 1.0)
    a = angle * w
    rel_x, rel_z = V[:, 0], V[:, 2] - body.z_sacrum
    out = V.copy()
    out[:, 0] = np.cos(a) * rel_x + np.sin(a) * rel_z
    out[:, 2] = body.z_sacrum - np.sin(a) * rel_x + np.cos(a) * rel_z
    return out


def back_hits(V: np.ndarray, triangles: np.ndarray, xz: np.ndarray):
    """Where rays along -Y from behind the body at ``xz`` (K, 2) mm first meet the skin: the back.

    Returns ``(triangle index (K,), barycentric weights (K, 3))``; a ray that misses has weights NaN.
    """
    from ..o3d import o3d

    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(V.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(triangles.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    xz = np.atleast_2d(xz)
    start = np.column_stack([xz[:, 0], np.full(len(xz), V[:, 1].max() + 10.0), xz[:, 1]])
    rays = np.concatenate([start, np.tile([0.0, -1.0, 0.0], (len(xz), 1))], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    ok = np.isfinite(hit["t_hit"].numpy())
    tri = np.where(ok, hit["primitive_ids"].numpy(), 0).astype(np.int64)
    uv = hit["primitive_uvs"].numpy().astype(float)
    w = np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])
    w[~ok] = np.nan
    return tri, w


def _onto_back(V: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The skin points straight behind ``points`` (mm world): the back at their x and z."""
    tri, w = back_hits(V, triangles, points[:, [0, 2]])
    return np.einsum("nk,nkd->nd", w, V[triangles[tri]])


def _turn_arms(V: np.ndarray, body: Body, abduction_deg: float) -> np.ndarray:
    """The arms turned about their shoulders in the coronal plane (+: raised), blended over the armpit."""
    out = V.copy()
    for k, side in enumerate((1.0, -1.0)):
        sh = body.arm_joints[k, 0]
        lateral = side * (V[:, 0] - sh[0])  # beyond the shoulder joint, outwards
        w = np.clip(lateral / 60.0, 0.0, 1.0) * (V[:, 2] > sh[2] - 700.0) * (V[:, 2] < sh[2] + 80.0)
        w *= side * V[:, 0] > 60.0  # never the trunk's middle
        a = np.radians(-side * abduction_deg) * w
        rel = V[:, [0, 2]] - sh[[0, 2]]
        c, sn = np.cos(a), np.sin(a)
        out[:, 0] = sh[0] + c * rel[:, 0] + sn * rel[:, 1]
        out[:, 2] = sh[2] - sn * rel[:, 0] + c * rel[:, 1]
        V = np.where(w[:, None] > 0, out, V)
        out = V.copy()
    return V


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) that turns direction ``a`` into direction ``b``: about their common normal."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    return rodrigues(axis / max(s, 1e-12) * np.arctan2(s, a @ b))


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _cross_arms(V: np.ndarray, body: Body) -> np.ndarray:
    """The arms folded in front of the chest, the forearms crossed (left over right), as a patient stands who
    holds their arms: each upper arm turned about its shoulder so that the elbow comes forward beside the front
    of the chest, each forearm (with its hand) turned about its elbow to point across the chest to the other
    side. The limbs keep their lengths; the skin blends between the moved and the still parts over the shoulder
    and the elbow (linear blend skinning). The forearms stand clear of the chest and belly in front of the
    sternum (at least 5 mm in tests/test_simulator_arms_crossed.py's builds) and hide the trunk's front from the
    cameras in front: the analysis sees a front that is not the trunk's. The upper arms may pass a few mm into a
    slim body's flanks (the skin is not pressed in), and the forearms into each other: surfaces inside the body
    are never seen, and scan_surface orients normals by the cameras that see them.
    """
    out = V.copy()
    k_size = (body.z_c7 - body.z_sacrum) / 480.0  # the body's size against the 1550 mm one the lengths are for
    torso_band = np.abs(V[:, 0]) < 110.0 * k_size
    for k, side in enumerate((1.0, -1.0)):
        S, E, W, F = body.arm_joints[k]
        upper, fore = np.linalg.norm(E - S), np.linalg.norm(W - E)
        # the skin of this arm: near its bones and beyond the trunk's side (the flank stays)
        d_upper = _segment_distance(V, S, E)
        d_fore = np.minimum(_segment_distance(V, E, W), _segment_distance(V, W, F))
        # (below the armpit the hanging arm's inner side lies about at the shoulder joint's x)
        lateral = (side * V[:, 0] - abs(S[0])) / k_size + 5.0
        arm = (1.0 - _smoothstep((np.minimum(d_upper, d_fore) / k_size - 60.0) / 20.0)) * _smoothstep(lateral / 20.0)
        # and everything far beyond the shoulder down to the fingertips (the thumb stands off the fingers' line;
        # the hips never reach so far out; the feet, below, do)
        arm = np.maximum(arm, _smoothstep((lateral - 75.0) / 30.0) * (V[:, 2] > F[2] - 80.0 * k_size))
        # along the upper arm: 0 at the shoulder joint, blended in over the first quarter
        t_upper = ((V - S) @ (E - S)) / upper ** 2
        w_upper = arm * _smoothstep(t_upper / 0.25)
        # the forearm side of the elbow, blended over 25 mm either side of it
        t_elbow = ((V - E) @ (W - E)) / fore
        w_fore = arm * _smoothstep((t_elbow / k_size + 25.0) / 50.0) * (d_fore < d_upper + 40.0 * k_size)
        # where the elbow goes: forward beside the front of the chest at about its old height
        z_e = S[2] - 0.78 * upper
        band = torso_band & (np.abs(V[:, 2] - z_e) < 50.0 * k_size)
        front = V[band, 1].min()
        Et = np.array([side * 0.9 * abs(S[0]), front - 45.0 * k_size, 0.0])
        Et[2] = S[2] - np.sqrt(max(upper ** 2 - (Et[0] - S[0]) ** 2 - (Et[1] - S[1]) ** 2, 1.0))
        R_u = _rotation_between(E - S, Et - S)
        E_new = S + R_u @ (E - S)
        # the forearm across the chest to the other side, the left one above and in front of the right
        target = np.array([-side * 0.95 * abs(S[0]), E_new[1] - 12.0 * k_size * side, E_new[2] + 22.0 * k_size * side])
        R_f = _rotation_between(R_u @ (W - E), target - E_new) @ R_u
        moved_upper = S + (V - S) @ R_u.T
        moved_fore = E_new + (V - E) @ R_f.T
        moved = (1.0 - w_fore)[:, None] * moved_upper + w_fore[:, None] * moved_fore
        w = np.maximum(w_upper, w_fore)[:, None]
        # each vertex belongs to one side's arm at most
        mine = side * V[:, 0] > 0
        out[mine] = ((1.0 - w) * V + w * moved)[mine]
    return out


# --- the curve ----------------------------------------------------------------

def _bump(s, lo, apex, hi):
    """Smooth bump: 1 at ``apex``, 0 outside (lo, hi), cos^2 flanks of their own widths."""
    s = np.asarray(s, float)
    left = np.clip((apex - s) / max(apex - lo, 1e-9), 0, 1)
    right = np.clip((s - apex) / max(hi - apex, 1e-9), 0, 1)
    return np.cos(0.5 * np.pi * np.where(s < apex, left, right)) ** 2


def curve_profiles(s, cfg: SubjectConfig, rotation_deg: float, lateral_mm: float):
    """Lateral deviation (mm, +right) and axial rotation (deg, +right) at spine levels ``s``."""
    if cfg.curve == "C":
        main = _bump(s, 0.0, cfg.thoracic_apex, 1.0)
        shape = main
    elif cfg.curve == "S":
        main = _bump(s, 0.38, cfg.thoracic_apex, 1.0)
        secondary = _bump(s, 0.0, cfg.lumbar_apex, 0.42)
        shape = main - cfg.secondary_ratio * secondary
    else:
        raise ValueError(f"unknown curve pattern {cfg.curve!r}: choose 'C' or 'S'")
    return lateral_mm * shape, rotation_deg * shape


@dataclass(frozen=True)
class Posture:
    """What differs between two captures of a subject."""

    rotation_deg: float  # axial rotation at the main apex
    lateral_mm: float  # lateral deviation at the main apex
    breathing: float  # -0.5 .. 0.5 of the full chest excursion
    growth: float  # relative stature change against the rest body
    R: np.ndarray  # placement and sway: rotation about the rig centre on the floor
    t: np.ndarray  # and translation (mm)

    def to_dict(self):
        return {"rotation_deg": self.rotation_deg, "lateral_mm": self.lateral_mm,
                "breathing": self.breathing, "growth": self.growth,
                "R": self.R.tolist(), "t": self.t.tolist()}


def pose_body(body: Body, cfg: SubjectConfig, posture: Posture):
    """Vertices of the posed subject (N, 3), its spine line (K, 3) and C7/sacrum points.

    Order: growth (about the feet), curve (per section about the spine),
    breathing, then rigid placement and sway.
    """
    g = posture.growth
    scale = np.array([1 + g / 2, 1 + g / 2, 1 + g])
    V = body.vertices * scale
    spine = body.spine * scale
    z_sac, z_c7 = body.z_sacrum * (1 + g), body.z_c7 * (1 + g)
    s = (V[:, 2] - z_sac) / (z_c7 - z_sac)
    lateral, rot = curve_profiles(s, cfg, posture.rotation_deg, posture.lateral_mm)
    sx = np.interp(V[:, 2], spine[:, 2], spine[:, 0])
    sy = np.interp(V[:, 2], spine[:, 2], spine[:, 1])
    rel = V[:, :2] - np.column_stack([sx, sy])
    # arms and hands move with the section they hang from, as a translation
    limit = 150.0 * (1 + g / 2)
    rel_c = np.column_stack([np.clip(rel[:, 0], -limit, limit), rel[:, 1]])
    phi = -np.radians(rot)  # +rotation (right) turns clockwise seen from above
    c, sn = np.cos(phi), np.sin(phi)
    turned = np.column_stack([c * rel_c[:, 0] - sn * rel_c[:, 1], sn * rel_c[:, 0] + c * rel_c[:, 1]])
    delta = turned - rel_c
    delta[:, 0] -= lateral  # + lateral is the patient's right, -X
    # rib prominence on the convex side of the back
    convex = -np.sign(rot) * rel_c[:, 0]  # distance towards the convex side (mm)
    hump = cfg.hump_mm_per_deg * np.abs(rot) * np.exp(-0.5 * ((convex - 70.0) / 40.0) ** 2)
    hump *= np.clip(rel_c[:, 1] / 40.0, 0, 1)  # back only
    delta[:, 1] += hump
    # breathing: the chest wall moves along its horizontal outward direction
    chest = _bump(s, 0.3, 0.68, 1.02)
    r = np.linalg.norm(rel_c, axis=1) + 1e-9
    outward = rel_c / r[:, None]
    front_weight = 1.0 / 3.0 + (2.0 / 3.0) * np.clip(-outward[:, 1], 0, 1)
    excursion = posture.breathing * cfg.breathing_mm * chest * front_weight
    delta += outward * excursion[:, None]
    V = V.copy()
    V[:, :2] += delta
    # the spine line follows the curve
    ss = (spine[:, 2] - z_sac) / (z_c7 - z_sac)
    lat_s, _ = curve_profiles(ss, cfg, posture.rotation_deg, posture.lateral_mm)
    spine = spine.copy()
    spine[:, 0] -= lat_s
    V = V @ posture.R.T + posture.t
    spine = spine @ posture.R.T + posture.t
    return V, spine


def skin_albedo(vertices_rest: np.ndarray, cfg: SubjectConfig, rng: np.random.Generator) -> np.ndarray:
    """Per-vertex skin albedo: mean ``cfg.albedo`` with slow variation (40–200 mm waves)."""
    waves = rng.normal(size=(6, 3))
    waves /= np.linalg.norm(waves, axis=1, keepdims=True)
    lengths = rng.uniform(40.0, 200.0, 6)
    phases = rng.uniform(0, 2 * np.pi, 6)
    field = np.sin(vertices_rest @ (waves / lengths[:, None]).T * 2 * np.pi + phases).sum(axis=1) / np.sqrt(3.0)
    return cfg.albedo * (1.0 + cfg.albedo_variation * np.clip(field, -2.5, 2.5))
