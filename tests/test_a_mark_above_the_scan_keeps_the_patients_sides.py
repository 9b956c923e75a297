"""A clinician's vertebra prominens marked at or just above the top of a scan cut at C7 must not turn the
patient frame: once the trunk's axis read at the mark's own height (a few shoulder-top points) lay beside
the neck, and the frame turned by 88 deg."""

import numpy as np
import pytest

from analysis.indices import analyse_torso
from analysis.synthetic import scan_surface
from recon_engine.simulator.bodies import Posture, load_makehuman, pose_body
from recon_engine.simulator.config import SubjectConfig
from recon_engine.simulator.rig import rotation_about


@pytest.fixture(scope="module")
def cut_at_c7():
    body = load_makehuman(1550.0, subdivisions=1)
    R = rotation_about([0, 0, 1], 15.0)
    V, _ = pose_body(body, SubjectConfig(), Posture(8.0, 3.2, 0.0, 0.0, R, np.zeros(3)))
    z = V[body.triangles].mean(axis=1)[:, 2]
    region = (z > body.z_sacrum - 60) & (z < body.z_c7 + 2)
    return scan_surface(V, body.triangles, region, n_points=30_000, seed=3), R @ np.array([0.0, 1.0, 0.0])


def test_a_mark_beside_the_depth_axis_does_not_turn_the_frame(cut_at_c7):
    from analysis.frame import detect_posterior

    torso, truth = cut_at_c7
    side = np.array([-truth[1], truth[0], 0.0])  # the patient's side, not the back
    post, info = detect_posterior(torso.points, prior={"posterior": side.tolist(), "back_towards": [],
                                                       "source": "clinician"})
    assert post @ truth > 0.98 and info["method"] == "shape"


def test_it_keeps_the_frame_when_only_one_shoulder_reaches_the_marks_height(cut_at_c7):
    from analysis.torso import make_torso

    torso, truth = cut_at_c7
    # the field of view cut one shoulder lower than the other: the top 40 mm hold the right shoulder only
    P, N = torso.points, torso.normals
    side = np.array([-truth[1], truth[0], 0.0])
    top = P[:, 2].max()
    keep = ~((P[:, 2] > top - 40.0) & ((P[:, :2] - np.median(P[:, :2], axis=0)) @ side[:2] > -60.0))
    lopsided = make_torso(P[keep], N[keep])
    auto = analyse_torso(lopsided).report
    mark = np.asarray(auto["landmarks"]["vertebra_prominens"]["position_mm"], float)
    mark[2] = top + 3.0
    rep = analyse_torso(lopsided, landmarks={"vertebra_prominens": mark.tolist()}).report
    assert np.asarray(rep["frame"]["posterior"]) @ truth > 0.98
