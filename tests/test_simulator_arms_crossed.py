"""The simulator's subjects with their forearms crossed in front of the chest (issue 27 §1: arm positions)."""

from dataclasses import replace

import numpy as np
import pytest

from recon_engine.o3d import o3d
from recon_engine.simulator.bodies import load_makehuman, make_parametric, shape_body
from recon_engine.simulator.config import SubjectConfig, preset
from recon_engine.simulator.posed import posed_subject, posture_like


@pytest.fixture(scope="module")
def rest():
    return load_makehuman(1550.0, subdivisions=0)


def _first_hits(V, T, origins, direction):
    """Where rays from ``origins`` along ``direction`` first meet the mesh: (points, triangle ids), NaN/-1 if not."""
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(V.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(T.astype(np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    rays = np.column_stack([origins, np.tile(direction, (len(origins), 1))]).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    ok = np.isfinite(t)
    return np.where(ok[:, None], origins + t[:, None] * direction, np.nan), np.where(ok, hit["primitive_ids"].numpy(), -1)


@pytest.mark.parametrize("build", [dict(), dict(build_width=0.88, build_depth=0.85, stature_mm=1300.0),
                                   dict(build_width=1.2, build_depth=1.35, belly_mm=18.0, breasts_mm=30.0, hips=1.1)])
def test_the_forearms_hide_the_front_of_the_chest_and_stand_clear_of_it(rest, build):
    body = rest if build.get("stature_mm", 1550.0) == 1550.0 else load_makehuman(build["stature_mm"], subdivisions=0)
    crossed = shape_body(body, SubjectConfig(arms_crossed=True, **build))
    V, T = crossed.vertices, crossed.triangles
    # rays from in front (-Y) towards the back, over the chest's middle, between the armpits and the waist
    z = np.linspace(body.z_sacrum + 0.45 * (body.z_c7 - body.z_sacrum), body.z_c7 - 60.0, 40)
    x = np.linspace(-60.0, 60.0, 9)
    X, Z = np.meshgrid(x, z)
    origins = np.column_stack([X.ravel(), np.full(X.size, -1000.0), Z.ravel()])
    hits, tri = _first_hits(V, T, origins, np.array([0.0, 1.0, 0.0]))
    on_arm = (tri >= 0) & ~crossed.torso_faces[np.maximum(tri, 0)]
    # some band of the chest is covered across its middle by the forearms
    covered_rows = on_arm.reshape(X.shape).all(axis=1)
    assert covered_rows.sum() >= 4, covered_rows
    # behind each forearm hit, the trunk's own front lies at least 5 mm further back (no forearm inside the chest)
    trunk_hits, _ = _first_hits(V, T[crossed.torso_faces], origins[on_arm], np.array([0.0, 1.0, 0.0]))
    gap = trunk_hits[:, 1] - hits[on_arm, 1]
    assert np.nanmin(gap) > 5.0, np.nanmin(gap)


def test_the_back_and_the_truth_stay_where_they_were(rest):
    drawn = shape_body(rest, SubjectConfig(dimples_mm=3.0))
    crossed = shape_body(rest, SubjectConfig(dimples_mm=3.0, arms_crossed=True))
    # the trunk below the armpits does not move: the back, the flanks, the front under the forearms
    below = rest.vertices[:, 2] < rest.arm_joints[0, 0, 2] - 120.0
    trunk = np.zeros(len(rest.vertices), bool)
    trunk[np.unique(rest.triangles[rest.torso_faces])] = True
    moved = np.linalg.norm(crossed.vertices - drawn.vertices, axis=1)
    assert moved[trunk & below].max() < 1e-9
    np.testing.assert_allclose(crossed.dimples, drawn.dimples)
    # the true landmarks (skin points behind C7 and the sacrum) as a capture's truth finds them: no arm in the way
    base = preset("paper")
    marks = [posed_subject(c, posture=posture_like(c, 8.0, 12.0))["landmarks"]
             for c in (replace(base, subject=SubjectConfig(arms_crossed=x)) for x in (False, True))]
    for key in ("vertebra_prominens", "sacral_point"):
        np.testing.assert_allclose(marks[1][key], marks[0][key])


def test_each_hand_moves_as_one_rigid_piece(rest):
    crossed = shape_body(rest, SubjectConfig(arms_crossed=True))
    for k in range(2):
        wrist, tip = rest.arm_joints[k, 2], rest.arm_joints[k, 3]
        hand = np.linalg.norm(rest.vertices - 0.5 * (wrist + tip), axis=1) < 0.4 * np.linalg.norm(tip - wrist)
        assert hand.sum() > 30
        a, b = rest.vertices[hand], crossed.vertices[hand]
        d_before = np.linalg.norm(a[:, None] - a[None], axis=2)
        d_after = np.linalg.norm(b[:, None] - b[None], axis=2)
        assert np.abs(d_after - d_before).max() < 1e-6
        assert np.linalg.norm(b.mean(axis=0) - a.mean(axis=0)) > 150.0  # it did move: across the chest


def test_it_rejects_crossed_arms_on_the_parametric_torso():
    with pytest.raises(ValueError, match="arms_crossed"):
        shape_body(make_parametric(1550.0, n_around=60, n_up=40), SubjectConfig(torso="parametric", arms_crossed=True))


def test_it_rejects_crossed_arms_with_an_abduction(rest):
    with pytest.raises(ValueError, match="arm_abduction_deg 0 \\(it is 20"):
        shape_body(rest, SubjectConfig(arms_crossed=True, arm_abduction_deg=20.0))
