"""What real patients and rigs bring (issue 29 §2): marks on the skin, underwear, highlights, exposure, JPEG, jitter."""

import json
from dataclasses import replace

import numpy as np
import pytest

from recon_engine.camera import Camera
from recon_engine.formats import load_images, read_capture, read_rig
from recon_engine.simulator.bodies import load_body
from recon_engine.simulator.config import ConditionsConfig, ProjectorConfig, SubjectConfig, preset
from recon_engine.simulator.render import Lighting, PreparedLighting, Scene, Surface
from recon_engine.simulator.rig import Projector, look_at
from recon_engine.simulator.scenario import simulate
from recon_engine.simulator.skin import FABRIC_MM, clothe, make_skin_marks


@pytest.fixture(scope="module")
def body():
    return load_body(SubjectConfig())


def _back_point(body, height_above_sacrum):
    """The rest body's skin point in the middle of the back at that height (the vertex nearest it)."""
    V = body.vertices
    z = body.z_sacrum + height_above_sacrum
    near = np.abs(V[:, 2] - z) < 5.0
    back = near & (np.abs(V[:, 0] - body.spine[:, 0].mean()) < 15.0)
    return V[back][np.argmax(V[back][:, 1])]


def test_no_condition_draws_no_marks_and_leaves_the_body_alone(body):
    cond = ConditionsConfig()
    assert make_skin_marks(body, cond, np.random.default_rng(0), 0.5) is None
    assert clothe(body, cond) is body


def test_freckles_and_moles_darken_spots_and_leave_most_skin_as_it_was(body):
    cond = ConditionsConfig(freckles_per_dm2=30.0, moles=15)
    marks = make_skin_marks(body, cond, np.random.default_rng(1), 0.5)
    m = marks.texture
    assert m.max() <= 1.0 + 1e-6
    assert 0.2 < m.min() < 0.5  # a mole: 65 % darker at its centre
    assert np.mean(m < 0.99) < 0.05  # spots, not a grey skin
    # the texture moves with the rest body: a point's multiplier is what the texture holds there
    p = _back_point(body, 200.0)
    assert 0.0 < marks.sample(p[None])[0] <= 1.0


def test_underwear_is_white_fabric_below_its_edge_and_stands_off_the_skin(body):
    cond = ConditionsConfig(underwear_top_mm=20.0)
    marks = make_skin_marks(body, cond, np.random.default_rng(2), 0.5)
    below, above = _back_point(body, -30.0), _back_point(body, 80.0)
    assert marks.sample(below[None])[0] == pytest.approx(0.75 / 0.5, rel=0.05)  # white cotton on 0.5 skin
    assert marks.sample(above[None])[0] == pytest.approx(1.0)
    clothed = clothe(body, cond)
    moved = np.linalg.norm(clothed.vertices - body.vertices, axis=1)
    z = body.vertices[:, 2] - body.z_sacrum
    assert moved[z < 15.0].max() == pytest.approx(FABRIC_MM, abs=1e-6)
    assert moved[z > 25.0].max() == 0.0


def test_oily_skin_adds_a_highlight_where_the_skin_mirrors_the_projector_into_the_camera():
    pc = ProjectorConfig(width=64, height=48, distance_mm=1500.0, coverage_mm=1500.0, black_level=0.0)
    P = np.array([0.0, -200.0, 1500.0])
    model = Camera(64, 48, 64.0, 64.0, 31.5, 23.5, np.zeros(5), look_at(P, [0, 0, 0], up=(0, 1, 0)), P)
    lighting = PreparedLighting(Lighting(ambient=0.0, projectors=(Projector("P", "A", model, np.ones((48, 64),
                                                                                                  np.float32)),),
                                         projector_cfg=pc))
    V = np.array([[-2000, -2000, 0.0], [2000, -2000, 0.0], [2000, 2000, 0.0], [-2000, 2000, 0.0]])
    scene = Scene([Surface("skin", V, np.array([[0, 1, 2], [0, 2, 3]]), albedo=np.full(4, 0.5))])
    eye = np.array([0.0, 200.0, 1500.0])  # the mirror image of the projector about the plane's normal at y = 0
    pos = np.array([[0.0, 0.0, 0.0], [600.0, 600.0, 0.0], [-600.0, 500.0, 0.0]])
    normal = np.tile([0.0, 0.0, 1.0], (3, 1))
    valid, kinds = np.ones(3, bool), np.ones(3, bool)
    E0, S0 = lighting.irradiance(scene, pos, normal, valid, kinds, eye, 0.0)
    E, S = lighting.irradiance(scene, pos, normal, valid, kinds, eye, 0.08, 30.0)
    assert np.array_equal(E, E0) and not S0.any()  # matte skin: nothing added, the diffuse light unchanged
    assert S[0] > 0.08 * E[0] and S[0] > 10 * S[1:].max()  # the highlight is at the mirror point only


def _tiny(tmp_path, name, **conditions):
    cfg = preset("tiny", seed=5, captures=(("visit0-a", 0),), torso_cameras=("A2", "A3"),
                 conditions=ConditionsConfig(**conditions))
    cfg = replace(cfg, testfield=replace(cfg.testfield, poses=0))
    out = tmp_path / name
    simulate(out, cfg, progress=lambda m: None, workers=1)
    return out


def test_a_camera_one_stop_over_is_twice_as_bright_and_jpeg_is_stored_as_asked(tmp_path):
    clean = _tiny(tmp_path, "clean")
    off = _tiny(tmp_path, "off", exposure_ev=(("A3", 1.0),), jpeg_quality=90)
    rig = read_rig(clean / "rig.json")
    a, b = (load_images(read_capture(s / "captures" / "visit0-a", rig), rig) for s in (clean, off))
    assert set(a) == set(b) == {"A2", "A3"}  # only the cameras asked for; the others are missing, as the spec allows
    manifest = json.loads((off / "captures" / "visit0-a" / "capture.json").read_text())
    assert all(e["file"].endswith(".jpg") for e in manifest["images"])
    lit = (a["A3"] > 20) & (a["A3"] < 100)  # neither dark nor near saturation
    ratio = np.median(b["A3"][lit].astype(float) / a["A3"][lit])
    assert 1.8 < ratio < 2.2
    same = np.abs(b["A2"].astype(float) - a["A2"]).mean()
    assert same < 2.0  # the other camera: the same image, but for JPEG's loss


def test_trigger_jitter_shows_each_camera_the_body_at_its_own_instant(tmp_path):
    still = _tiny(tmp_path, "still")
    moving = _tiny(tmp_path, "moving", trigger_jitter_ms=100.0, sway_speed_mm_s=300.0)
    rig = read_rig(still / "rig.json")
    a, b = (load_images(read_capture(s / "captures" / "visit0-a", rig), rig) for s in (still, moving))
    # about 30 mm of sway between the instants: silhouettes and the pattern's parallax move in both images
    # (measured 9.5-10.7 DN on average; a motion of hundredths of a mm changes the shot noise's draws: 0.7-0.9 DN)
    assert np.abs(a["A2"].astype(float) - b["A2"]).mean() > 4.0
    assert np.abs(a["A3"].astype(float) - b["A3"]).mean() > 4.0


def test_it_names_an_exposure_offset_for_a_camera_the_rig_lacks(tmp_path):
    with pytest.raises(ValueError, match="exposure_ev.*Z9"):
        _tiny(tmp_path, "bad", exposure_ev=(("Z9", 1.0),))
