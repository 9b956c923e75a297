"""The sagittal angles, the Cobb-angle estimate and the lumbar dimples on shapes whose answer is known."""

import numpy as np
import pytest

from analysis.backsurface import DepthMap
from analysis.indices import withhold
from analysis.landmarks import find_dimples
from analysis.profiles import cobb_estimate, pelvic_figures, sagittal_angles, tangent_turns


def _profile(u):
    """A back seen from the side: sacral crest, lordosis's hollow at 0.3, kyphosis's crest at 0.75 (mm)."""
    return 12 * np.cos(2 * np.pi * (u - 0.75) / 0.9)


def test_it_reads_the_kyphotic_and_lordotic_angles_of_a_known_profile():
    z_sp, L = 800.0, 450.0
    z = np.arange(z_sp - 40, z_sp + L + 40, 4.0)
    u = (z - z_sp) / L
    got = sagittal_angles(z, _profile(u), z_sp, z_sp + L, smooth_mm=1.0)
    fine = np.linspace(0.05, 0.95, 2001)
    angle = np.degrees(np.arctan(np.gradient(_profile(fine), fine * L)))
    kyph = angle[(fine > 0.3) & (fine < 0.75)].max() - angle[fine > 0.75].min()
    lord = angle[(fine > 0.3) & (fine < 0.75)].max() - angle[fine < 0.3].min()
    assert got["kyphotic_angle_deg"] == pytest.approx(kyph, abs=0.5)
    assert got["lordotic_angle_deg"] == pytest.approx(lord, abs=0.5)
    assert got["levels"]["kyphotic_apex"] == pytest.approx(0.75, abs=0.02)
    assert got["levels"]["lordotic_apex"] == pytest.approx(0.3, abs=0.02)


def test_it_reads_no_sagittal_angle_from_a_profile_that_stops_half_way():
    z = np.arange(800.0, 1000.0, 4.0)
    assert sagittal_angles(z, np.zeros_like(z), 800.0, 1250.0) is None


@pytest.mark.parametrize("sign, side", [(1.0, "right"), (-1.0, "left")])
def test_it_estimates_the_cobb_angle_of_a_c_curve_and_its_side(sign, side):
    z_sp, L, A = 800.0, 450.0, 20.0
    z = np.linspace(z_sp, z_sp + L, 41)
    lateral = sign * A * np.sin(np.pi * (z - z_sp) / L)  # + towards the patient's right
    got = cobb_estimate(z, lateral, z_sp, z_sp + L, smooth_mm=2.0)
    assert len(got["curves"]) == 1
    major = got["major"]
    assert major["value_deg"] == pytest.approx(2 * np.degrees(np.arctan(A * np.pi / L)), abs=0.6)
    assert major["side"] == side and got[side] == major and got["left" if side == "right" else "right"] is None
    assert major["apex_level"] == pytest.approx(0.5, abs=0.03)
    assert major["region"] == "thoracic" and not got["double_major"]


def _s_curve(z, z_sp, L, upper, lower):
    """A right thoracic curve of amplitude ``upper`` (mm) over the top 60 % and a left lumbar one of ``lower``
    over the bottom 40 %: each a half sine, so each curve's Cobb angle is 2·atan(amplitude·pi / span)."""
    u = (z - z_sp) / L
    return np.where(u >= 0.4, upper * np.sin(np.pi * (u - 0.4) / 0.6), -lower * np.sin(np.pi * u / 0.4))


def test_it_gives_both_curves_of_an_s_each_with_its_side_and_region():
    z_sp, L = 800.0, 450.0
    z = np.linspace(z_sp, z_sp + L, 91)
    got = cobb_estimate(z, _s_curve(z, z_sp, L, 20.0, 8.0), z_sp, z_sp + L, smooth_mm=2.0)
    lumbar, thoracic = got["curves"]  # bottom to top
    assert (lumbar["side"], lumbar["region"]) == ("left", "thoracolumbar/lumbar")
    assert (thoracic["side"], thoracic["region"]) == ("right", "thoracic")
    # the thoracic half sine is the steeper at the inflection, so its own tangents there and at the top bound it
    assert thoracic["value_deg"] == pytest.approx(2 * np.degrees(np.arctan(20.0 * np.pi / (0.6 * L))), abs=1.0)
    assert lumbar["lower_level"] < lumbar["apex_level"] < lumbar["upper_level"] <= thoracic["lower_level"] + 0.02
    assert got["major"] is thoracic and got["right"] is thoracic and got["left"] is lumbar
    assert not got["double_major"]


def test_it_calls_two_nearly_equal_curves_a_double_major():
    z_sp, L = 800.0, 450.0
    z = np.linspace(z_sp, z_sp + L, 91)
    # a lumbar curve over 40 % of the trunk with 2/3 of the thoracic one's amplitude bends about as much
    got = cobb_estimate(z, _s_curve(z, z_sp, L, 15.0, 10.0), z_sp, z_sp + L, smooth_mm=2.0)
    assert abs(got["right"]["value_deg"] - got["left"]["value_deg"]) < 5.0
    assert got["double_major"]


def test_it_makes_no_curve_of_noise_on_a_straight_spine():
    z_sp, L = 800.0, 450.0
    z = np.linspace(z_sp, z_sp + L, 91)
    rng = np.random.default_rng(3)
    got = cobb_estimate(z, rng.normal(0.0, 1.0, len(z)), z_sp, z_sp + L)
    assert got["curves"] == [] and got["major"] is None and not got["double_major"]


def test_tangent_turns_ignores_a_wiggle_smaller_than_the_swing():
    theta = np.array([0.0, 4.0, 8.0, 7.0, 8.5, 10.0, 2.0, -6.0, -5.0])
    assert tangent_turns(theta, 3.0) == [0, 5, 7]
    assert tangent_turns(np.zeros(5), 3.0) == []


def test_it_tells_the_right_side_of_the_pelvis_higher_as_positive():
    left, right = np.array([45.0, 70, 850]), np.array([-45.0, 70, 858])
    got = pelvic_figures(left, right, 10.0, 14.0)
    assert got["pelvic_obliquity_mm"] == pytest.approx(8.0)
    assert got["pelvic_obliquity_deg"] == pytest.approx(np.degrees(np.arctan2(8, 90)))
    assert got["pelvic_torsion_deg"] == pytest.approx(4.0)


def _back(dimples_mm, left=(45.0, 860.0), right=(-45.0, 866.0), seed=0, extra=()):
    """A depth map of a convex lower back (patient frame) with two round hollows (and ``extra`` ones)."""
    x = np.arange(-150.0, 150.1, 2.0)
    z = np.arange(760.0, 1000.1, 2.0)
    Z, X = np.meshgrid(z, x, indexing="ij")
    depth = 90 - X ** 2 / 400.0 - 4.0 * np.exp(-0.5 * (X / 8.0) ** 2)  # convex across, a spinal furrow
    for cx, cz in (left, right, *extra):
        depth = depth - dimples_mm * np.exp(-0.5 * (((X - cx) / 11.0) ** 2 + ((Z - cz) / 14.0) ** 2))
    depth = depth + np.random.default_rng(seed).normal(0, 0.02, depth.shape)
    return DepthMap(x, z, depth)


def test_it_suggests_a_pair_of_clear_dimples_where_they_are_but_leaves_them_to_the_clinician():
    z = np.arange(760.0, 1000.0, 4.0)
    found = find_dimples(_back(6.0), 830.0, 450.0, (z, np.zeros_like(z)))
    assert found["dimple_confidence"] == "low"
    assert found["dimple_method"].startswith("suggested") and "rival" not in found["dimple_method"]
    # to a fraction of the depth map's 2 mm cells
    assert np.allclose(found["dimple_left"][[0, 2]], [45, 860], atol=1.5)
    assert np.allclose(found["dimple_right"][[0, 2]], [-45, 866], atol=1.5)


def test_it_is_not_confident_of_dimples_on_a_smooth_back():
    z = np.arange(760.0, 1000.0, 4.0)
    found = find_dimples(_back(0.0), 830.0, 450.0, (z, np.zeros_like(z)))
    assert found["dimple_confidence"] == "low" and found["dimple_method"] == "hollows too shallow"


def test_it_says_when_another_hollow_is_as_deep_as_the_dimples():
    z = np.arange(760.0, 1000.0, 4.0)
    found = find_dimples(_back(6.0, extra=[(60.0, 900.0)]), 830.0, 450.0, (z, np.zeros_like(z)))
    assert found["dimple_confidence"] == "low" and "a rival hollow nearby" in found["dimple_method"]


def test_it_tells_both_reasons_when_two_kinds_of_figure_are_withheld():
    rep = {"hump_mm": 3.0, "pelvic_obliquity_mm": 2.0}
    withhold(rep, "the facing is uncertain", ("hump_mm",), landmarks=["vertebra_prominens"])
    withhold(rep, "the dimples are not seen", ("pelvic_obliquity_mm",), landmarks=["dimple_left"])
    assert rep["hump_mm"] is None and rep["pelvic_obliquity_mm"] is None
    nm = rep["not_measurable"]
    assert nm["indices"] == ["hump_mm", "pelvic_obliquity_mm"]
    assert "facing" in nm["reason"] and "dimples" in nm["reason"]
    assert nm["mark"] == ["vertebra_prominens", "dimple_left"]


def test_a_figure_withheld_in_its_regions_too_leaves_the_others():
    def rep():
        return {"surface_rotation_deg": {"rms": 1.0, "max": 2.0},
                "regions": {"thoracic": {"surface_rotation_deg": {"rms": 1.0, "max": 2.0},
                                         "lateral_deviation_mm": {"rms": 3.0, "max": 4.0}}}}
    r = withhold(rep(), "the apex is unread", ("surface_rotation_deg",), in_regions=True)
    assert r["surface_rotation_deg"] == {"rms": None, "max": None}
    assert r["regions"]["thoracic"]["surface_rotation_deg"] == {"rms": None, "max": None}
    assert r["regions"]["thoracic"]["lateral_deviation_mm"] == {"rms": 3.0, "max": 4.0}
    kept = withhold(rep(), "the apex is unread", ("surface_rotation_deg",))
    assert kept["regions"]["thoracic"]["surface_rotation_deg"]["max"] == 2.0
