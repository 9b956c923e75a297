"""Write a complete simulated scenario in the capture-format spec, with its truth.

Layout of ``OUT``::

    rig.json, testfield.json                      # as the rig would ship them
    captures/testfield-pose<k>/                   # test-field capture bundles
    captures/<name>/                              # torso capture bundles
    truth/scenario.json                           # every parameter and the seed
    truth/calibration.json                        # true IOPs/EOPs at calibration time (engine terms;
                                                  # the whole lens in each camera's simulator_lens key)
    truth/testfield.json                          # true marker corners (tower frame)
    truth/testfield_poses.json                    # tower pose k -> world (= pose 0 frame)
    truth/<name>/calibration.json                 # true cameras at that capture (arms displaced)
    truth/<name>/body.ply, torso.ply              # posed subject, whole and the torso region
    truth/<name>/truth.json                       # posture, arm displacements, spine, landmarks
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..formats import Calibration, write_calibration, write_capture, write_json, write_rig, write_testfield
from ..parallel import start_worker_process
from .bodies import Posture, curve_profiles, load_body, pose_body, skin_albedo
from .config import ScenarioConfig
from .render import Lighting, PreparedLighting, Scene, Surface, render
from .rig import apply_lens_changes, displace, draw_arm_displacements, make_rig, rotation_about
from .skin import clothe, make_skin_marks
from .testfield import Tower, draw_poses, make_tower, surveyed

CAPTURED_AT = "2026-11-22T09:00:00+00:00"


def _background(cfg: ScenarioConfig, rng: np.random.Generator) -> list[Surface]:
    """A dim, mottled room wall beyond the rig and the floor."""
    sc = cfg.scene
    n_around, n_up = 96, 12
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    z = np.linspace(0, 2600, n_up)
    aa, zz = np.meshgrid(a, z)
    V = np.column_stack([sc.wall_radius_mm * np.cos(aa.ravel()), sc.wall_radius_mm * np.sin(aa.ravel()), zz.ravel()])
    i, j = np.meshgrid(np.arange(n_up - 1), np.arange(n_around), indexing="ij")
    p0 = i * n_around + j
    p1 = i * n_around + (j + 1) % n_around
    T = np.vstack([np.column_stack([p0.ravel(), (p0 + n_around).ravel(), p1.ravel()]),
                   np.column_stack([p1.ravel(), (p0 + n_around).ravel(), (p1 + n_around).ravel()])])
    wall = Surface("wall", V, T, albedo=sc.wall_albedo * rng.uniform(0.6, 1.4, len(V)))
    ring = np.column_stack([sc.wall_radius_mm * np.cos(a), sc.wall_radius_mm * np.sin(a), np.zeros(n_around)])
    Vf = np.vstack([ring, [0, 0, 0]])
    Tf = np.column_stack([np.full(n_around, n_around), np.arange(n_around), (np.arange(n_around) + 1) % n_around])
    floor = Surface("floor", Vf, Tf, albedo=sc.floor_albedo * rng.uniform(0.8, 1.2, len(Vf)))
    return [wall, floor]


def _tower_surface(tower: Tower, pose) -> Surface:
    R, t = pose
    return Surface("tower", tower.vertices @ R.T + t, tower.triangles, tower=tower, pose=(R, t))


def _write_ply(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    from ..o3d import o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    if not o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=False):
        raise OSError(f"{path}: could not write PLY")


def _calibration(rig_serial: str, cameras: dict, frame: str, lenses: dict | None = None) -> Calibration:
    """The true calibration in the spec's format: the engine's terms of each true lens.

    The whole true lens (with the terms the engine's model lacks: thin prism,
    higher decentring, skew) goes into each camera's ``simulator_lens`` key,
    which the spec's readers ignore (unknown keys); the engine-model fields
    hold the true lens's own values of those terms, so a comparison with this
    truth carries the model error honestly.
    """
    extra = {}
    if lenses:
        extra["camera_extra"] = {c: {"simulator_lens": lenses[c].to_dict()} for c in cameras if c in lenses}
    return Calibration(rig=rig_serial, calibrated_at=CAPTURED_AT, frame=frame, cameras=dict(cameras), extra=extra)


def draw_posture(cfg: ScenarioConfig, rng: np.random.Generator, visit: int, placement) -> Posture:
    sc = cfg.subject
    R_place, t_place = placement
    tilt_axis = np.array([*rng.normal(0, 1, 2), 0.0])
    R_sway = rotation_about(tilt_axis, rng.uniform(-sc.sway_tilt_deg, sc.sway_tilt_deg)) @ \
        rotation_about([0, 0, 1], rng.uniform(-sc.sway_yaw_deg, sc.sway_yaw_deg))
    t_sway = np.array([*rng.uniform(-sc.sway_shift_mm, sc.sway_shift_mm, 2), 0.0])
    rotation = sc.rotation_deg + visit * sc.progression_deg
    lateral = sc.lateral_mm * rotation / sc.rotation_deg if sc.rotation_deg else sc.lateral_mm
    return Posture(rotation_deg=rotation, lateral_mm=lateral, breathing=rng.uniform(-0.5, 0.5),
                   growth=visit * sc.growth, R=R_sway @ R_place, t=R_sway @ t_place + t_sway)


def _landmark(scene: Scene, spine_point, posterior) -> list:
    """The skin point behind a spine point (ray from inside the body towards the back)."""
    start = np.asarray(spine_point, float)
    t = scene.distance(start, posterior[None, :])[0]
    return (start + t * posterior).tolist() if np.isfinite(t) else None


def _render_group(job):
    """Render some cameras of one capture (runs in a worker process).

    ``surfaces`` is one list for every camera, or camera -> list when the
    cameras saw the subject at different instants (trigger jitter).
    """
    surfaces, lighting, subsurface, cameras, lenses, cc, exposures, seeds, prnu_seeds, specular = job
    prepared = PreparedLighting(lighting, subsurface)
    shared = Scene(surfaces) if isinstance(surfaces, list) else None
    return {c: render(shared or Scene(surfaces[c]), cam, prepared, cc, np.random.default_rng(seeds[c]),
                      exposures[c], prnu_seed=prnu_seeds[c], lens=lenses[c], specular=specular[0],
                      shininess=specular[1])[0]
            for c, cam in cameras.items()}


def _at_trigger(body, cfg: ScenarioConfig, posture: Posture, cameras, rng: np.random.Generator) -> dict:
    """Camera -> the posed vertices at its own trigger instant (``trigger_jitter_ms`` about the capture's).

    Between the instants the subject sways (a straight drift at
    ``sway_speed_mm_s``) and breathes (a sine of ``breathing_period_s`` through
    the capture's breathing phase, rising or falling at random).
    """
    cond = cfg.conditions
    heading = rng.uniform(0, 2 * np.pi)
    velocity = cond.sway_speed_mm_s * np.array([np.cos(heading), np.sin(heading), 0.0])  # mm/s
    b = np.clip(posture.breathing, -0.5, 0.5)
    breathing_rate = rng.choice([-1.0, 1.0]) * 2 * np.pi / cond.breathing_period_s * np.sqrt(0.25 - b ** 2)  # 1/s
    out = {}
    for c in cameras:
        dt = rng.normal(0.0, cond.trigger_jitter_ms) / 1000.0  # s
        moved = replace(posture, breathing=posture.breathing + breathing_rate * dt, t=posture.t + velocity * dt)
        out[c] = pose_body(body, cfg.subject, moved)[0]
    return out


def simulate(out: str | Path, cfg: ScenarioConfig, force: bool = False, progress=print,
             workers: int | None = None) -> dict:
    """Simulate ``cfg`` into the folder ``out``; returns a summary of what was written.

    The scenario is written into a temporary folder beside ``out`` and renamed
    at the end, so an interrupted run leaves no half-written scenario. Cameras
    are rendered in ``workers`` processes (default: one per core); every
    camera's noise has its own seed, so the images do not depend on ``workers``.
    """
    n_workers = max(1, workers or os.cpu_count() or 1)
    pool = None
    if n_workers > 1:
        # a killed command must not leave its render workers behind, and each worker one thread per pool
        pool = ProcessPoolExecutor(n_workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=start_worker_process)
    try:
        return _simulate(out, cfg, force, progress, n_workers, pool)
    finally:
        if pool:
            pool.shutdown()


def _simulate(out, cfg, force, progress, n_workers, pool) -> dict:
    out = Path(out)
    if out.exists():
        if not force:
            raise FileExistsError(f"{out}: already exists (use --force to replace it)")
    tmp = out.with_name(out.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    t_start = time.perf_counter()
    # the installation (rig, test field, patient, room) comes from the seed; what
    # differs between sessions (test-field poses, arm swings, posture, noise)
    # from the seed and the session, so two sessions share one rig
    rng_rig, rng_tf, rng_body, rng_bg = (np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(4))
    rng_poses, rng_arms, rng_pose, rng_place = (
        np.random.default_rng(s) for s in np.random.SeedSequence([cfg.seed, 1000 + cfg.session]).spawn(4))

    cond = cfg.conditions
    # conditions draw from streams of their own: the marks belong to the patient (the seed), the trigger
    # instants to the session
    rng_marks = np.random.default_rng(np.random.SeedSequence([cfg.seed, 3000]))
    rng_jitter = np.random.default_rng(np.random.SeedSequence([cfg.seed, 4000 + cfg.session]))
    body = clothe(load_body(cfg.subject), cond)
    albedo = skin_albedo(body.vertices, cfg.subject, rng_body)
    marks = make_skin_marks(body, cond, rng_marks, cfg.subject.albedo)
    centre_z = 0.5 * (body.z_sacrum + body.z_c7)
    truth = apply_lens_changes(make_rig(cfg, rng_rig, centre_z), cfg.lens_changes)
    tower = make_tower(cfg.testfield, rng_tf)
    testfield = surveyed(tower, cfg.testfield, rng_tf)
    poses = draw_poses(cfg.testfield, rng_poses)
    background = _background(cfg, rng_bg)
    rig = truth.rig

    write_rig(tmp / "rig.json", rig)
    write_testfield(tmp / "testfield.json", testfield)
    (tmp / "truth").mkdir()
    write_calibration(tmp / "truth" / "calibration.json", _calibration(rig.serial, truth.cameras, "testfield pose 0", truth.lenses))
    write_testfield(tmp / "truth" / "testfield.json",
                    type(testfield)(testfield.name, testfield.aruco_dictionary, tower.corners, 0.0))
    write_json(tmp / "truth" / "testfield_poses.json", {
        "frame": "world = testfield pose 0",
        "poses": [{"pose": k, "R": R.tolist(), "t": t.tolist()} for k, (R, t) in enumerate(poses)]})

    summary = {"out": str(out), "preset": cfg.preset, "seed": cfg.seed, "session": cfg.session,
               "captures": [], "timings_s": {}}
    cc = cfg.camera

    ev = dict(cond.exposure_ev)
    unknown = sorted(set(ev) - set(rig.camera_ids))
    if unknown:
        raise ValueError(f"conditions.exposure_ev: no camera {', '.join(unknown)} in the rig")
    image_kw = dict(ext="jpg", jpeg_quality=cond.jpeg_quality) if cond.jpeg_quality else {}

    def render_capture(name, surfaces, lighting, subsurface, cameras, exposure, capture_kw, only=(), specular=(0.0, 30.0)):
        t0 = time.perf_counter()
        capture_index = len(summary["captures"])
        all_ids = rig.camera_ids
        ids = [c for c in all_ids if not only or c in only]
        groups = [ids[k::n_workers] for k in range(n_workers)]
        jobs = [(surfaces if isinstance(surfaces, list) else {c: surfaces[c] for c in g}, lighting, subsurface,
                 {c: cameras[c] for c in g}, {c: truth.lenses[c] for c in g}, cc,
                 {c: exposure / 2.0 ** ev.get(c, 0.0) for c in g},  # +1 EV: twice the light per DN
                 {c: (cfg.seed, cfg.session, 1, capture_index, all_ids.index(c)) for c in g},
                 {c: (cfg.seed, 2, all_ids.index(c)) for c in g}, specular) for g in groups if g]
        images = {}
        for part in (pool.map(_render_group, jobs) if pool else map(_render_group, jobs)):
            images.update(part)
        images = {c: images[c] for c in ids}
        dest = tmp / "captures" / name
        dest.parent.mkdir(parents=True, exist_ok=True)
        write_capture(dest, rig=rig.serial, captured_at=CAPTURED_AT, images=images, **capture_kw, **image_kw)
        dt = time.perf_counter() - t0
        summary["timings_s"][name] = round(dt, 2)
        summary["captures"].append(f"captures/{name}")
        progress(f"  {name}: {len(images)} images in {dt:.1f} s")
        return images

    # --- test field captures: room light, projectors off
    tf_cfg = cfg.testfield
    tf_light = Lighting(ambient=tf_cfg.ambient, key=tf_cfg.key_light)
    for k, pose in enumerate(poses if tf_cfg.poses else []):
        render_capture(f"testfield-pose{k}", [_tower_surface(tower, pose), *background], tf_light, 0.0,
                       truth.cameras, 0.6, dict(kind="testfield", testfield=testfield.name, pose=k))

    # --- torso captures: all projectors on, arms B.. displaced
    placements = {}
    for name, visit in cfg.captures:
        if visit not in placements:
            yaw = rng_place.uniform(-cfg.subject.visit_yaw_deg, cfg.subject.visit_yaw_deg)
            shift = np.array([*rng_place.uniform(-cfg.subject.visit_shift_mm, cfg.subject.visit_shift_mm, 2), 0.0])
            placements[visit] = (rotation_about([0, 0, 1], yaw), shift)
        posture = draw_posture(cfg, rng_pose, visit, placements[visit])
        V, spine = pose_body(body, cfg.subject, posture)
        skin = Surface("skin", V, body.triangles, albedo=albedo, marks=marks, rest=body.vertices)
        scene = Scene([skin, *background])  # for the landmarks below
        seen = [skin, *background]
        if cond.trigger_jitter_ms > 0:
            shown = [c for c in rig.camera_ids if not cfg.torso_cameras or c in cfg.torso_cameras]
            seen = {c: [Surface("skin", Vc, body.triangles, albedo=albedo, marks=marks, rest=body.vertices),
                        *background] for c, Vc in _at_trigger(body, cfg, posture, shown, rng_jitter).items()}
        displacement = draw_arm_displacements(cfg, rng_arms, truth)
        cameras, projectors = displace(truth, displacement)
        lighting = Lighting(ambient=cfg.scene.torso_ambient, projectors=tuple(projectors[a.id] for a in rig.arms),
                            projector_cfg=cfg.projector)
        render_capture(name, seen, lighting, cfg.subject.subsurface_mm, cameras,
                       (cond.exposure_albedo or cfg.subject.albedo) * (cfg.projector.power + cfg.scene.torso_ambient),
                       dict(kind="torso"),
                       only=cfg.torso_cameras, specular=(cond.specular, cond.shininess))
        tdir = tmp / "truth" / name
        tdir.mkdir(parents=True)
        write_calibration(tdir / "calibration.json", _calibration(rig.serial, cameras, "testfield pose 0", truth.lenses))
        _write_ply(tdir / "body.ply", V, body.triangles)
        _write_ply(tdir / "torso.ply", V, body.triangles[body.torso_faces])
        posterior = posture.R @ np.array([0.0, 1.0, 0.0])
        levels = np.linspace(0, 1, 21)
        lateral, rotation = curve_profiles(levels, cfg.subject, posture.rotation_deg, posture.lateral_mm)
        write_json(tdir / "truth.json", {
            "visit": visit,
            "posture": posture.to_dict(),
            "arm_displacements": {a: {"R": d["R"].tolist(), "t": d["t"].tolist(), "yaw_deg": d["yaw_deg"]}
                                  for a, d in displacement.items()},
            "displacement_convention": "X_displaced = R @ X_calibrated + t (world frame, mm)",
            "spine": spine.tolist(),
            "landmarks": {"vertebra_prominens": _landmark(scene, spine[-1], posterior),
                          "sacral_point": _landmark(scene, spine[0], posterior)},
            "curve": {"pattern": cfg.subject.curve, "levels": levels.tolist(),
                      "lateral_mm": lateral.tolist(), "rotation_deg": rotation.tolist(),
                      "convention": "level 0 = sacrum, 1 = C7; +lateral and +rotation towards the patient's right"},
        })

    summary["timings_s"]["total"] = round(time.perf_counter() - t_start, 2)
    write_json(tmp / "truth" / "scenario.json", {"config": cfg.to_dict(), "summary": summary,
                                                  "body": body.name, "mesh_triangles": int(len(body.triangles))})
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return summary
