"""Visit-to-visit comparison on a known rigid motion plus a local bump; repeatability and MDC."""

import numpy as np
import pytest

from analysis.compare import compare_torsos, write_comparison
from analysis.repeatability import exceeds_mdc, index_changes, mdc_from_comparisons, mdc_from_index_pairs
from analysis.rigid import rotation_from_vector
from analysis.synthetic import synthetic_back
from analysis.torso import make_torso


@pytest.fixture(scope="module")
def pair():
    earlier, _ = synthetic_back(rotation_deg=6.0, spacing_mm=4.0, noise_mm=0.05, seed=1)
    later0, _ = synthetic_back(rotation_deg=6.0, spacing_mm=4.0, noise_mm=0.05, seed=2)
    P = later0.points.copy()
    # a 6 mm bump on the right upper back (patient's right is -X)
    c = np.array([-60.0, 95.0, 1200.0])
    r = np.linalg.norm((P - c)[:, [0, 2]], axis=1)
    back = P[:, 1] > 40
    P[:, 1] += np.where(back, 6.0 * np.exp(-0.5 * (r / 30.0) ** 2), 0.0)
    # then the whole later torso moved: 3 deg about a tilted axis, 15 mm
    R = rotation_from_vector(np.radians(3.0) * np.array([0.2, 0.1, 1.0]) / np.linalg.norm([0.2, 0.1, 1.0]))
    t = np.array([12.0, -8.0, 5.0])
    later = make_torso(P @ R.T + t)
    return earlier, later, R, t, c


def test_rigid_motion_recovered_despite_bump(pair, tmp_path):
    earlier, later, R, t, c = pair
    res = compare_torsos(earlier, later)
    rep = res["report"]
    Rm, tm = np.array(rep["transform"]["R"]), np.array(rep["transform"]["t"])
    # the estimated transform undoes the motion
    assert np.allclose(Rm @ R, np.eye(3), atol=2e-3)
    assert np.allclose(Rm @ t + tm, 0.0, atol=1.0)
    d = res["deformation_mm"]
    near = np.linalg.norm((res["points"] - c)[:, [0, 2]], axis=1) < 10
    near &= res["points"][:, 1] > 40
    assert np.nanmean(d[near]) == pytest.approx(6.0, abs=1.0)  # outward: positive
    far = np.linalg.norm((res["points"] - c)[:, [0, 2]], axis=1) > 120
    assert np.nanmedian(np.abs(d[far])) < 0.2
    assert rep["format"] == "torso-comparison/1"
    assert set(rep["signed_distance_mm"]) == {"mean", "p05", "p95"}
    assert rep["matched_fraction"] > 0.9
    assert rep["regions"]["back_upper"]["mean"] > rep["regions"]["back_lower"]["mean"]
    assert rep["regions"]["back_right"]["p95"] > 2.0
    paths = write_comparison(tmp_path, res)
    from recon_engine.surface import read_ply

    ply = read_ply(paths["deformation"])
    assert ply["data"]["deformation_mm"].shape == (len(later),)


def test_growth_reported():
    a, _ = synthetic_back(spacing_mm=4.0, seed=3)
    b, _ = synthetic_back(spacing_mm=4.0, seed=4, length_mm=492.0)
    rep = compare_torsos(a, b)["report"]
    assert rep["growth"]["change"]["trunk_length_mm"] == pytest.approx(12.0, abs=3.0)


def test_mdc_from_repeat_pairs():
    pairs = [({"hump_mm": 5.0, "lateral_deviation_mm": {"rms": 3.0, "max": 6.0}},
              {"hump_mm": 5.4, "lateral_deviation_mm": {"rms": 3.2, "max": 5.5}}),
             ({"hump_mm": 7.0, "lateral_deviation_mm": {"rms": 4.0, "max": 8.0}},
              {"hump_mm": 6.8, "lateral_deviation_mm": {"rms": 4.1, "max": 8.3}})]
    mdc = mdc_from_index_pairs(pairs)
    sem = np.sqrt((0.4 ** 2 + 0.2 ** 2) / 4)
    assert mdc["hump_mm"]["sem"] == pytest.approx(sem)
    assert mdc["hump_mm"]["mdc_estimate"] == pytest.approx(1.96 * np.sqrt(2) * sem)
    # changes are judged against the upper bound of the estimate's 95 % interval (two pairs: x6.3)
    assert mdc["hump_mm"]["mdc"] == pytest.approx(mdc["hump_mm"]["ci95"][1])
    assert mdc["hump_mm"]["mdc"] == pytest.approx(6.29 * mdc["hump_mm"]["mdc_estimate"], rel=1e-3)
    ch = index_changes(pairs[0][0], {"hump_mm": 9.0, "lateral_deviation_mm": {"rms": 3.0, "max": 6.1}}, mdc)
    assert ch["hump_mm"]["exceeds_mdc"] is True
    assert ch["lateral_deviation_mm.max"]["exceeds_mdc"] is False
    assert exceeds_mdc(1.0, None) is None
    m2 = mdc_from_comparisons([{"signed_distance_mm": {"mean": 0.1}, "average_normal_distance_mm": 0.3}])
    assert m2["signed_distance_mm.mean"]["mdc_estimate"] == pytest.approx(0.196)


def test_growth_and_indices_read_the_same_trunk_length_as_each_torsos_own_report(pair):
    from analysis.indices import analyse_torso

    earlier, later, *_ = pair
    rep = compare_torsos(earlier, later)["report"]
    own = analyse_torso(later).report
    assert rep["growth"]["later"]["trunk_length_mm"] == pytest.approx(own["trunk_length_mm"], abs=1e-9)
    assert rep["growth"]["earlier"]["trunk_length_mm"] == pytest.approx(analyse_torso(earlier).report["trunk_length_mm"],
                                                                         abs=1e-9)
