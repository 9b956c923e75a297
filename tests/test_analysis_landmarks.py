"""Landmarks with a confidence: found where the shape shows them, declared not measurable where it does not."""

import numpy as np
import pytest

from analysis.indices import analyse_torso
from tests.test_analysis_facing import scan


@pytest.fixture(scope="module")
def body():
    from recon_engine.simulator.bodies import load_makehuman

    return load_makehuman(1550.0, subdivisions=1)


def test_it_finds_both_landmarks_with_confidence_when_the_neck_and_the_sacrum_are_seen(body):
    torso, _ = scan(body, 20.0, "hips-to-chin", rotation_deg=6.0)
    rep = analyse_torso(torso).report
    for k in ("vertebra_prominens", "sacral_point"):
        assert rep["landmarks"][k]["confidence"] == "high"
    withheld = (rep.get("not_measurable") or {}).get("indices", [])
    assert "trunk_length_mm" not in withheld and rep["trunk_length_mm"] > 350


def test_it_declares_the_indices_not_measurable_when_the_scan_starts_above_the_sacrum(body):
    torso, _ = scan(body, 0.0, "waist-to-head", rotation_deg=6.0)
    rep = analyse_torso(torso).report
    assert rep["landmarks"]["sacral_point"]["confidence"] == "low"
    # the sacral point first; the lumbar dimples are asked for too (automatic ones are never trusted)
    assert rep["not_measurable"]["mark"] in (["sacral_point"], ["sacral_point", "dimple_left", "dimple_right"])
    assert "mark the landmark" in rep["not_measurable"]["reason"]
    assert rep["surface_rotation_deg"]["max"] is None and rep["trunk_length_mm"] is None
    # the clinician marks it: the indices are measured again
    sp = np.asarray(rep["landmarks"]["sacral_point"]["position_mm"]) - [0.0, 0.0, 120.0]
    again = analyse_torso(torso, landmarks={"sacral_point": sp.tolist()}).report
    withheld = (again.get("not_measurable") or {}).get("indices", [])
    assert "surface_rotation_deg" not in withheld and "trunk_length_mm" not in withheld
    assert again["surface_rotation_deg"]["max"] > 2


def test_same_day_rescans_place_the_landmarks_within_5_mm(body):
    # two scans of the same subject, swayed by 1.2 deg and 4 mm and sampled anew: the landmarks' errors move
    # with the skin, not with the sampling
    from recon_engine.simulator.bodies import Posture, pose_body
    from recon_engine.simulator.config import SubjectConfig
    from recon_engine.simulator.rig import rotation_about
    from analysis.synthetic import scan_surface

    errors = []
    for k, (yaw, shift) in enumerate(((0.0, 0.0), (1.2, 4.0))):
        R = rotation_about([0, 0, 1], yaw)
        V, spine = pose_body(body, SubjectConfig(), Posture(8.0, 3.0, 0.0, 0.0, R, np.array([shift, -shift, 0.0])))
        z = V[body.triangles].mean(axis=1)[:, 2]
        region = (z > body.z_sacrum - 60) & (z < body.z_c7 + 160)
        rep = analyse_torso(scan_surface(V, body.triangles, region, n_points=60_000, seed=10 + k)).report
        pos = {n: np.asarray(rep["landmarks"][n]["position_mm"]) for n in ("vertebra_prominens", "sacral_point")}
        # each landmark in the subject's own frame (the sway undone)
        errors.append({n: R.T @ (p - [shift, -shift, 0.0]) for n, p in pos.items()})
    for n in ("vertebra_prominens", "sacral_point"):
        assert np.linalg.norm(errors[0][n] - errors[1][n]) < 5.0, n
