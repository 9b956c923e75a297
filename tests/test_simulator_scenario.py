"""A simulated tiny scenario follows the spec and is faithful to its truth."""

import json

import numpy as np
import pytest

from recon_engine.formats import load_images, read_calibration, read_capture, read_rig, read_testfield
from recon_engine.simulator.checks import marker_corner_errors, neighbour_ncc


@pytest.fixture(scope="session")
def scenario(torso_scenario):
    """The engine tests' tiny scenario (tests/conftest.py): three test-field poses, visit0-a and visit1-a."""
    from tests.conftest import TORSO_SCENARIO

    return torso_scenario, TORSO_SCENARIO


def test_it_writes_every_file_in_the_spec_format(scenario):
    out, cfg = scenario
    rig = read_rig(out / "rig.json")
    assert [a.id for a in rig.arms] == ["A", "B", "C", "D"]
    assert all(len(a.cameras) == 5 for a in rig.arms)
    tf = read_testfield(out / "testfield.json")
    assert len(tf.markers) == cfg.testfield.sides * cfg.testfield.rows * cfg.testfield.columns
    for k in range(cfg.testfield.poses):
        cap = read_capture(out / "captures" / f"testfield-pose{k}", rig)
        assert cap.kind == "testfield" and cap.pose == k and cap.testfield == tf.name
        images = load_images(cap, rig)
        assert set(images) == set(rig.camera_ids)
        assert all(im.shape == (cfg.camera.height, cfg.camera.width) and im.dtype == np.uint8
                   for im in images.values())
    for name in ("visit0-a", "visit1-a"):
        cap = read_capture(out / "captures" / name, rig)
        assert cap.kind == "torso"
        truth = json.loads((out / "truth" / name / "truth.json").read_text())
        assert (out / "truth" / name / "torso.ply").exists()
        read_calibration(out / "truth" / name / "calibration.json")
        assert truth["landmarks"]["vertebra_prominens"] is not None
    scenario_json = json.loads((out / "truth" / "scenario.json").read_text())
    assert scenario_json["config"]["seed"] == cfg.seed


def test_each_camera_has_its_own_lens_and_an_off_centre_principal_point(scenario):
    out, cfg = scenario
    cal = read_calibration(out / "truth" / "calibration.json")
    dists = np.array([c.dist for c in cal.cameras.values()])
    assert len(np.unique(dists[:, 0])) == len(dists)
    offsets = np.array([[c.cx - (c.width - 1) / 2, c.cy - (c.height - 1) / 2] for c in cal.cameras.values()])
    assert np.all(np.abs(offsets).max(axis=1) > 1e-3)
    fx = np.array([c.fx for c in cal.cameras.values()])
    assert fx.std() > 0


def test_reference_arm_stays_and_the_others_swing_rigidly(scenario):
    out, cfg = scenario
    cal = read_calibration(out / "truth" / "calibration.json")
    rig = read_rig(out / "rig.json")
    for name in ("visit0-a", "visit1-a"):
        truth = json.loads((out / "truth" / name / "truth.json").read_text())
        moved = read_calibration(out / "truth" / name / "calibration.json")
        disp = truth["arm_displacements"]
        assert disp["A"]["yaw_deg"] == 0.0
        assert all(0 < abs(disp[a]["yaw_deg"]) <= cfg.rig.arm_rotation_max_deg for a in "BCD")
        for arm in rig.arms:
            first = arm.cameras[0]
            for cam in arm.cameras:
                # relative orientation inside the arm is unchanged
                rel0 = cal.cameras[cam].R @ cal.cameras[first].R.T
                rel1 = moved.cameras[cam].R @ moved.cameras[first].R.T
                assert np.allclose(rel0, rel1, atol=1e-9)
                d0 = np.linalg.norm(cal.cameras[cam].C - cal.cameras[first].C)
                d1 = np.linalg.norm(moved.cameras[cam].C - moved.cameras[first].C)
                assert abs(d0 - d1) < 1e-6
            if arm.id == "A":
                assert np.allclose(moved.cameras[first].C, cal.cameras[first].C)
            else:
                assert not np.allclose(moved.cameras[first].C, cal.cameras[first].C)


def test_later_visit_has_the_chosen_progression(scenario):
    out, cfg = scenario
    t0 = json.loads((out / "truth" / "visit0-a" / "truth.json").read_text())
    t1 = json.loads((out / "truth" / "visit1-a" / "truth.json").read_text())
    assert t1["posture"]["rotation_deg"] - t0["posture"]["rotation_deg"] == pytest.approx(cfg.subject.progression_deg)
    assert t1["posture"]["growth"] > t0["posture"]["growth"]


def test_marker_corners_agree_with_the_truth_projection(scenario):
    """The renderer's geometry, measured independently of OpenCV's corner refinement."""
    out, cfg = scenario
    errors = marker_corner_errors(out)
    assert len(errors["edge_fit"]) > 1000
    assert np.median(errors["edge_fit"]) < 0.15
    # and OpenCV's own refinement is the biased one, as the issue says
    assert np.median(errors["opencv_subpix"]) > np.median(errors["edge_fit"])


def test_neighbouring_cameras_see_the_same_pattern(scenario):
    """Patches around truth-projected torso points correlate between neighbours."""
    out, cfg = scenario
    pairs = neighbour_ncc(out, "visit0-a")
    assert len(pairs) == 16  # 4 arms x 4 neighbouring pairs
    medians = np.array([p["median"] for p in pairs.values()])
    assert all(p["points"] > 100 for p in pairs.values())
    assert np.median(medians) > 0.9
    assert medians.min() > 0.8
