"""The true posed subject of a capture without rendering (for analysis tests and benchmarks).

``posed_subject`` gives the same posture, vertices and landmarks as
``simulate`` writes into ``truth/<name>/`` for the same configuration (seed,
session and capture list), in milliseconds instead of a render. World frame
as everywhere in the simulator: mm, Z up, the test field's pose 0 frame; the
subject at rest faces -Y with its left towards +X.
"""

from __future__ import annotations


import numpy as np

from .bodies import Posture, back_hits, curve_profiles, load_body, pose_body
from .config import ScenarioConfig


def draw_postures(cfg: ScenarioConfig) -> dict:
    """Posture of every torso capture of ``cfg`` (name -> Posture), drawn as ``simulate`` draws them."""
    from .scenario import draw_posture
    from .rig import rotation_about

    _, _, rng_pose, rng_place = (
        np.random.default_rng(s) for s in np.random.SeedSequence([cfg.seed, 1000 + cfg.session]).spawn(4))
    placements, out = {}, {}
    for name, visit in cfg.captures:
        if visit not in placements:
            yaw = rng_place.uniform(-cfg.subject.visit_yaw_deg, cfg.subject.visit_yaw_deg)
            shift = np.array([*rng_place.uniform(-cfg.subject.visit_shift_mm, cfg.subject.visit_shift_mm, 2), 0.0])
            placements[visit] = (rotation_about([0, 0, 1], yaw), shift)
        out[name] = draw_posture(cfg, rng_pose, visit, placements[visit])
    return out


def posed_subject(cfg: ScenarioConfig, capture: str | None = None, posture: Posture | None = None) -> dict:
    """The posed subject of one capture of ``cfg``, or of an explicit ``posture``.

    Returns ``{"vertices" (N, 3) mm world, "triangles" (M, 3), "torso_faces" (M,) bool, "spine" (K, 3),
    "posture", "landmarks": {"vertebra_prominens", "sacral_point"} (skin points behind C7 and the sacrum,
    found as ``simulate`` finds them, mm world) and, on a body with dimples, "dimple_left", "dimple_right"
    (the bottoms of the lumbar dimples, the patient's left and right), "curve": {"levels", "lateral_mm", "rotation_deg"},
    "symmetry_line": (L, 3) mm world}``. The symmetry line is the skin over the spinous processes: the
    rest body's skin point straight behind the spine at each height, carried through the posture
    (curve, hump, breathing, sway) with the skin itself.
    """
    if posture is None:
        postures = draw_postures(cfg)
        if capture not in postures:
            raise ValueError(f"no torso capture {capture!r} in the configuration (have {sorted(postures)})")
        posture = postures[capture]
    body = load_body(cfg.subject)
    V, spine = pose_body(body, cfg.subject, posture)
    posterior = posture.R @ np.array([0.0, 1.0, 0.0])
    landmarks = {}
    from ..o3d import o3d

    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(V.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(body.triangles.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    for key, p in (("vertebra_prominens", spine[-1]), ("sacral_point", spine[0])):
        ray = np.concatenate([p, posterior])[None].astype(np.float32)
        t = float(scene.cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])
        landmarks[key] = (np.asarray(p) + t * posterior) if np.isfinite(t) else None
    if body.dimples is not None:
        # the same skin point of the same triangle, carried through the posture
        tri, w = back_hits(body.vertices, body.triangles, body.dimples[:, [0, 2]])
        pts = np.einsum("nk,nkd->nd", w, V[body.triangles[tri]])
        landmarks["dimple_left"], landmarks["dimple_right"] = pts[0], pts[1]
    levels = np.linspace(0, 1, 21)
    lateral, rotation = curve_profiles(levels, cfg.subject, posture.rotation_deg, posture.lateral_mm)
    return {"vertices": V, "triangles": body.triangles, "torso_faces": body.torso_faces, "spine": spine,
            "posture": posture, "landmarks": landmarks,
            "curve": {"levels": levels, "lateral_mm": lateral, "rotation_deg": rotation},
            "symmetry_line": _symmetry_line(body, V)}


def _symmetry_line(body, V_posed: np.ndarray, n: int = 101) -> np.ndarray:
    """Posed skin points (L, 3) that lie straight behind the rest body's spine (+Y) from sacrum to C7."""
    from ..o3d import o3d

    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(body.vertices.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(body.triangles.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    z = np.linspace(body.z_sacrum, body.z_c7, n)
    start = np.column_stack([np.interp(z, body.spine[:, 2], body.spine[:, 0]),
                             np.interp(z, body.spine[:, 2], body.spine[:, 1]), z])
    rays = np.concatenate([start, np.tile([0.0, 1.0, 0.0], (n, 1))], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    ok = np.isfinite(hit["t_hit"].numpy())
    tri = body.triangles[hit["primitive_ids"].numpy()[ok].astype(np.int64)]
    uv = hit["primitive_uvs"].numpy()[ok].astype(float)
    w = np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])
    # the same barycentric point of the same triangle, on the posed skin
    return np.einsum("nk,nkd->nd", w, V_posed[tri])


def posture_like(cfg: ScenarioConfig, rotation_deg: float, lateral_mm: float | None = None, breathing: float = 0.0,
                 growth: float = 0.0, R=None, t=None) -> Posture:
    """A posture with a chosen curve severity, at rest in the rig centre unless ``R``, ``t`` are given.

    ``lateral_mm`` defaults to the configuration's ratio of lateral deviation to rotation.
    """
    sc = cfg.subject
    if lateral_mm is None:
        lateral_mm = sc.lateral_mm * rotation_deg / sc.rotation_deg if sc.rotation_deg else sc.lateral_mm
    return Posture(rotation_deg=float(rotation_deg), lateral_mm=float(lateral_mm), breathing=float(breathing),
                   growth=float(growth), R=np.eye(3) if R is None else np.asarray(R, float),
                   t=np.zeros(3) if t is None else np.asarray(t, float))


__all__ = ["draw_postures", "posed_subject", "posture_like"]
