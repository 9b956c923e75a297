"""Subjects: anatomy, the scoliotic curve, breathing and sway."""

import numpy as np
import pytest

from recon_engine.simulator.bodies import Posture, curve_profiles, load_makehuman, make_parametric, pose_body
from recon_engine.simulator.config import SubjectConfig


def _rest():
    return Posture(0.0, 0.0, 0.0, 0.0, np.eye(3), np.zeros(3))


@pytest.fixture(scope="module", params=["makehuman", "parametric"])
def body(request):
    if request.param == "makehuman":
        return load_makehuman(1550.0, subdivisions=0)
    return make_parametric(1550.0, n_around=120, n_up=90)


def test_it_stands_at_the_rig_centre_facing_minus_y(body):
    V = body.vertices
    assert V[:, 2].min() >= -1.0
    torso = V[np.unique(body.triangles[body.torso_faces])]
    # torso centred on the vertical axis; its back (spine side) towards +Y
    assert abs(torso[:, 0].mean()) < 15
    assert 780 < body.z_sacrum < 900 and 1250 < body.z_c7 < 1360
    # an adolescent torso: 24-40 cm wide, 15-26 cm deep
    assert 240 < np.ptp(torso[:, 0]) < 400 and 150 < np.ptp(torso[:, 1]) < 260


def test_no_curve_leaves_the_body_unchanged(body):
    V, spine = pose_body(body, SubjectConfig(), _rest())
    assert np.allclose(V, body.vertices)


def test_lateral_deviation_moves_the_spine_towards_the_right_at_the_apex(body):
    cfg = SubjectConfig(curve="C", thoracic_apex=0.6, lateral_mm=15.0, rotation_deg=0.0)
    posture = Posture(0.0, 15.0, 0.0, 0.0, np.eye(3), np.zeros(3))
    V, spine = pose_body(body, cfg, posture)
    lat, rot = curve_profiles(np.array([0.0, 0.6, 1.0]), cfg, 0.0, 15.0)
    assert lat == pytest.approx([0.0, 15.0, 0.0])
    # patient's right is -X
    z_apex = body.z_sacrum + 0.6 * (body.z_c7 - body.z_sacrum)
    near = np.abs(body.vertices[:, 2] - z_apex) < 5
    assert np.allclose(V[near, 0] - body.vertices[near, 0], -15.0, atol=0.3)


def test_axial_rotation_raises_a_rib_hump_on_the_convex_side(body):
    cfg = SubjectConfig(curve="C", thoracic_apex=0.6, rotation_deg=12.0, lateral_mm=0.0, hump_mm_per_deg=0.0)
    V, _ = pose_body(body, cfg, Posture(12.0, 0.0, 0.0, 0.0, np.eye(3), np.zeros(3)))
    z_apex = body.z_sacrum + 0.6 * (body.z_c7 - body.z_sacrum)
    band = np.abs(body.vertices[:, 2] - z_apex) < 8
    back = band & (body.vertices[:, 1] > 0)
    right = back & (body.vertices[:, 0] < -50) & (body.vertices[:, 0] > -110)
    left = back & (body.vertices[:, 0] > 50) & (body.vertices[:, 0] < 110)
    # right back moves posteriorly (+Y), left back anteriorly
    assert (V[right, 1] - body.vertices[right, 1]).mean() > 5
    assert (V[left, 1] - body.vertices[left, 1]).mean() < -5


def test_s_curve_has_opposite_lumbar_and_thoracic_curves():
    cfg = SubjectConfig(curve="S")
    lat, rot = curve_profiles(np.array([cfg.lumbar_apex, cfg.thoracic_apex]), cfg, 10.0, 12.0)
    assert lat[1] == pytest.approx(12.0) and lat[0] == pytest.approx(-12.0 * cfg.secondary_ratio)
    assert rot[1] == pytest.approx(10.0) and rot[0] < 0


def test_breathing_moves_the_chest_front_more_than_the_back(body):
    cfg = SubjectConfig(breathing_mm=3.0)
    V, _ = pose_body(body, cfg, Posture(0.0, 0.0, 0.5, 0.0, np.eye(3), np.zeros(3)))
    d = np.linalg.norm(V - body.vertices, axis=1)
    z_chest = body.z_sacrum + 0.68 * (body.z_c7 - body.z_sacrum)
    band = np.abs(body.vertices[:, 2] - z_chest) < 10
    rel_y = body.vertices[:, 1] - np.interp(body.vertices[:, 2], body.spine[:, 2], body.spine[:, 1])
    front = band & (rel_y < -60) & (np.abs(body.vertices[:, 0]) < 60)
    back = band & (rel_y > 15) & (np.abs(body.vertices[:, 0]) < 60)
    assert d[front].mean() == pytest.approx(1.5, abs=0.3)
    assert d[back].mean() < 0.5 * d[front].mean()


def test_growth_and_placement_are_applied():
    body = make_parametric(1550.0, n_around=60, n_up=40)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    V, spine = pose_body(body, SubjectConfig(), Posture(0.0, 0.0, 0.0, 0.02, R, np.array([10.0, 0, 0])))
    assert V[:, 2].max() == pytest.approx(body.vertices[:, 2].max() * 1.02)
    assert np.allclose(spine[:, :2], (body.spine * [1.01, 1.01, 1.02])[:, :2] @ R[:2, :2].T + [10, 0], atol=1e-6)


def test_the_true_symmetry_line_turns_with_the_section_about_the_spine():
    """The skin over the spinous processes: at rest straight behind the spine, turned with the section."""
    from dataclasses import replace

    from recon_engine.simulator.config import preset
    from recon_engine.simulator.posed import posed_subject

    cfg = preset("tiny")
    cfg = replace(cfg, subject=replace(cfg.subject, curve="C", thoracic_apex=0.6, hump_mm_per_deg=0.0))
    rest = posed_subject(cfg, posture=Posture(0.0, 0.0, 0.0, 0.0, np.eye(3), np.zeros(3)))
    turned = posed_subject(cfg, posture=Posture(10.0, 0.0, 0.0, 0.0, np.eye(3), np.zeros(3)))
    spine = rest["spine"]
    P0, P1 = rest["symmetry_line"], turned["symmetry_line"]
    x_spine = np.interp(P0[:, 2], spine[:, 2], spine[:, 0])
    y_spine = np.interp(P0[:, 2], spine[:, 2], spine[:, 1])
    assert np.allclose(P0[:, 0], x_spine, atol=1e-6) and np.all(P0[:, 1] > y_spine)
    s = (P0[:, 2] - spine[0, 2]) / (spine[-1, 2] - spine[0, 2])
    k = np.argmin(np.abs(s - 0.6))
    depth = P0[k, 1] - y_spine[k]
    # +rotation (the right back comes backwards) carries the skin over the spine to the patient's left (+X)
    assert P1[k, 0] - P0[k, 0] == pytest.approx(depth * np.sin(np.radians(10.0)), rel=0.05)


def test_the_body_mesh_ships_with_the_repository(monkeypatch):
    # a user's fresh clone has nothing beside the repository: the simulator's mesh must be inside it
    from pathlib import Path

    from recon_engine.simulator.bodies import mesh_path

    monkeypatch.delenv("TORSOSCAN_MAKEHUMAN_OBJ", raising=False)
    repo = Path(__file__).resolve().parents[1]
    path = mesh_path()
    assert path.exists() and repo in path.resolve().parents
    assert (path.parent / "makehuman-LICENSE.ASSETS.md").exists()
