"""A scan that stops on the neck shows no neck hollow: its VP is a suggestion, and the indices wait for a mark.

On such a scan the midline's "hollow" is only where the seen surface stops, and the half-depth level of the neck's
flank lies too low (the paper preset's torso region, cut at C7, placed VP 31-33 mm from the simulator's point
with high confidence).
"""

import numpy as np
import pytest

from analysis.indices import analyse_torso
from analysis.synthetic import scan_surface
from recon_engine.simulator.bodies import Posture, load_makehuman, pose_body
from recon_engine.simulator.config import SubjectConfig
from tests.test_analysis_facing import clicked


@pytest.fixture(scope="module")
def posed():
    body = load_makehuman(1550.0, subdivisions=1)
    V, _ = pose_body(body, SubjectConfig(), Posture(8.0, 3.0, 0.0, 0.0, np.eye(3), np.zeros(3)))
    return body, V


def _scan(posed, top_above_c7_mm):
    body, V = posed
    z = V[body.triangles].mean(axis=1)[:, 2]
    region = (z > body.z_sacrum - 60) & (z < body.z_c7 + top_above_c7_mm)
    return scan_surface(V, body.triangles, region, n_points=60_000, seed=3)


def test_it_asks_for_the_vertebra_prominens_when_the_scan_stops_on_the_neck(posed):
    rep = analyse_torso(_scan(posed, 30.0)).report
    vp = rep["landmarks"]["vertebra_prominens"]
    assert vp["confidence"] == "low" and "hollow not seen" in vp["method"]
    assert "vertebra_prominens" in rep["not_measurable"]["mark"]
    assert rep["surface_rotation_deg"]["max"] is None and rep["trunk_length_mm"] is None


def test_it_trusts_the_vertebra_prominens_when_the_neck_is_seen_up_to_the_head(posed):
    rep = analyse_torso(_scan(posed, 160.0)).report
    assert rep["landmarks"]["vertebra_prominens"]["confidence"] == "high"
    assert rep["landmarks"]["vertebra_prominens"]["method"] == "neck flank"


def test_a_marked_vertebra_prominens_measures_the_indices_again(posed):
    body, V = posed
    torso = _scan(posed, 30.0)
    mark = clicked(torso, body.z_c7 - 5.0, np.array([0.0, 1.0, 0.0]))  # the subject faces -Y: its back is +Y
    rep = analyse_torso(torso, landmarks={"vertebra_prominens": mark.tolist()}).report
    assert rep["landmarks"]["vertebra_prominens"]["source"] == "clinician"
    withheld = (rep.get("not_measurable") or {}).get("indices", [])
    assert "surface_rotation_deg" not in withheld and rep["surface_rotation_deg"]["max"] > 2
    assert abs(rep["landmarks"]["vertebra_prominens"]["position_mm"][2] - mark[2]) < 3.0
