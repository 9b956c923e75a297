"""Epipolar resampling: conjugate points on one row, exact maps back to the original images."""

import numpy as np
import pytest

from recon_engine.epipolar import rectify_pair, rig_centre, subject_depth_bounds
from recon_engine.formats import read_calibration


@pytest.fixture(scope="module")
def truth(torso_scenario):
    return read_calibration(torso_scenario / "truth" / "visit0-a" / "calibration.json")


def _surface_points(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([-200, -200, 800], [200, 200, 1400], (n, 3))


@pytest.mark.parametrize("pair", [("A1", "A2"), ("B2", "B3"), ("D4", "D5")])
def test_conjugate_points_share_a_row(truth, pair):
    a, b = truth.cameras[pair[0]], truth.cameras[pair[1]]
    p = rectify_pair(a, b)
    X = _surface_points()
    ra, rb = p.to_rectified("left", a.project(X)), p.to_rectified("right", b.project(X))
    assert np.median(np.abs(ra[:, 1] - rb[:, 1])) < 0.05
    assert np.max(np.abs(ra[:, 1] - rb[:, 1])) < 1e-6


def test_rectified_coordinates_map_back_exactly(truth):
    a, b = truth.cameras["C2"], truth.cameras["C3"]
    p = rectify_pair(a, b)
    uv = a.project(_surface_points(500))
    assert np.max(np.abs(p.to_original("left", p.to_rectified("left", uv)) - uv)) < 1e-6


def test_the_resampling_maps_agree_with_the_exact_mapping(truth):
    p = rectify_pair(truth.cameras["A2"], truth.cameras["A3"])
    mx, my = p.maps("left")
    rows, cols = np.array([10, 100, 200]), np.array([30, 250, 400])
    exact = p.to_original("left", np.column_stack([cols, rows]).astype(float))
    assert np.allclose(np.column_stack([mx[rows, cols], my[rows, cols]]), exact, atol=2e-3)


def test_the_disparity_range_holds_the_subject(truth):
    p = rectify_pair(truth.cameras["B1"], truth.cameras["B2"])
    centre = rig_centre(list(truth.cameras.values()))
    d0, d1 = p.disparity_range(*subject_depth_bounds(p, centre, 400))
    X = centre + np.random.default_rng(1).normal(0, 120, (500, 3))
    d = p.to_rectified("left", p.left.project(X))[:, 0] - p.to_rectified("right", p.right.project(X))[:, 0]
    assert d0 <= d.min() and d.max() <= d1


def test_it_refuses_cameras_without_a_baseline(truth):
    with pytest.raises(ValueError, match="no baseline"):
        rectify_pair(truth.cameras["A1"], truth.cameras["A1"])
