"""The lateral deviation is measured from the symmetry line's own ends, not from the landmarks' x."""

import numpy as np
import pytest

from analysis.indices import analyse_torso
from analysis.synthetic import synthetic_back


@pytest.fixture(scope="module")
def curved():
    torso, _ = synthetic_back(lateral_mm=10.0, spacing_mm=3.5, noise_mm=0.05)
    return torso, analyse_torso(torso)


def test_a_sacral_point_clicked_off_the_midline_does_not_tilt_the_lateral_deviation(curved):
    torso, auto = curved
    left = np.asarray(auto.frame.R)[0]  # the patient's left in the rig frame
    sp = np.asarray(auto.report["landmarks"]["sacral_point"]["position_mm"]) + 6.0 * left
    clicked = analyse_torso(torso, landmarks={"sacral_point": sp.tolist()})
    a = np.array([s["lateral_deviation_mm"] for s in auto.report["sections"]])
    b = np.array([s["lateral_deviation_mm"] for s in clicked.report["sections"]])
    assert len(a) == len(b)
    # a click 6 mm to the side moved the lowest section's deviation by about 6 mm when the reference line ran
    # through the landmarks
    assert np.max(np.abs(a - b)) < 0.5
    assert clicked.report["lateral_deviation_mm"]["max"] == pytest.approx(auto.report["lateral_deviation_mm"]["max"],
                                                                           abs=0.5)
    # the trunk imbalance is the landmarks' own offset: it moves with the click
    assert clicked.report["trunk_imbalance_mm"] - auto.report["trunk_imbalance_mm"] == pytest.approx(6.0, abs=1.0)


def test_the_deviation_is_zero_at_the_lines_ends(curved):
    _, auto = curved
    s = auto.report["sections"]
    # the reference joins the line's points at SP and VP: the sections next to them read little deviation,
    # the apex of the 10 mm curve reads it all
    assert abs(s[0]["lateral_deviation_mm"]) < 2.0 and abs(s[-1]["lateral_deviation_mm"]) < 2.0
    assert auto.report["lateral_deviation_mm"]["max"] == pytest.approx(10.0, abs=2.0)
