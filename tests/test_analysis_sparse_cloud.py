"""The analysis on a sparse, clustered cloud (a reduced rig's features bunch on the pattern's blobs)."""

import numpy as np

from analysis.indices import analyse_torso
from analysis.synthetic import synthetic_back
from analysis.torso import Torso, point_spacing, sampling_spacing


def _clustered(torso: Torso, every_mm: float = 10.0, radius_mm: float = 2.6) -> Torso:
    """Only the points within ``radius_mm`` (across and up) of a lattice of blobs ``every_mm`` apart, as a
    reduced rig's matched features bunch on the projected pattern's blobs."""
    xz = torso.points[:, [0, 2]]
    near = np.linalg.norm(xz - every_mm * np.round(xz / every_mm), axis=1) < radius_mm
    return Torso(torso.points[near], torso.normals[near])


def test_it_finds_the_landmarks_on_a_clustered_cloud():
    dense, truth = synthetic_back(spacing_mm=2.0, noise_mm=0.05, seed=1)
    torso = _clustered(dense)
    # the nearest neighbour is as close as in the dense cloud, the area each point holds several times larger
    assert sampling_spacing(torso.points) > 1.7 * point_spacing(torso.points)
    lm = analyse_torso(torso).report["landmarks"]
    assert abs(lm["vertebra_prominens"]["position_mm"][2] - truth["vertebra_prominens_z"]) < 15
    assert abs(lm["sacral_point"]["position_mm"][2] - truth["sacral_point_z"]) < 15


def test_sampling_spacing_of_a_regular_grid_is_its_step():
    torso, _ = synthetic_back(spacing_mm=4.0)
    assert abs(sampling_spacing(torso.points) - 4.0) < 0.3
