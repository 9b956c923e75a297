"""ICPatch point-to-patch registration."""

import numpy as np
import pytest

from recon_engine.bundle import rodrigues
from recon_engine.registration import ICPatchConfig, Transform, icpatch
from recon_engine.surface import PointSurface
from tests.surface_pieces import moved, torso_like


def test_it_recovers_a_known_similarity():
    fixed = torso_like(-200, 100, n=20000, seed=1)
    part = torso_like(-50, 200, n=8000, seed=2, noise=0.05)
    truth = Transform(1.0005, rodrigues(np.radians([0.4, -0.3, 1.0])), np.array([4.0, -3.0, 2.0]))
    moving = moved(part, truth.inverse())  # what the other arm measured in its own frame
    res = icpatch(moving, fixed, cfg=ICPatchConfig(estimate_scale=True))
    T = res["transform"]
    err = T.apply(moving.points) - part.points
    assert res["converged"]
    # the patches are chords of a curved surface: a few hundredths of a mm of bias remain
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.08
    assert res["transform"].scale == pytest.approx(1.0005, abs=5e-4)
    # only the overlap is matched: about 150 of 250 mm
    assert 0.45 < res["matched_fraction"] < 0.7
    assert res["average_normal_distance_mm"] < 0.06
    assert 0 < res["sigmas"]["tx_mm"] < 0.05


def test_points_over_a_hole_are_not_paired():
    fixed = torso_like(-200, 100, n=20000, seed=3)
    hole = np.linalg.norm(fixed.points[:, :2] - [0, 0], axis=1) < 50
    keep = ~hole[fixed.faces].any(axis=1)
    fixed = PointSurface(fixed.points, fixed.normals, fixed.faces[keep])
    part = torso_like(-100, 100, n=8000, seed=4)
    res = icpatch(part, fixed, Transform(1.0, rodrigues(np.radians([0, 0, 0.3])), np.array([1.0, 0, 0])))
    err = res["transform"].apply(part.points) - part.points
    assert res["converged"] and np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.08


def test_it_refuses_surfaces_that_do_not_overlap():
    a = torso_like(-200, -100, seed=5)
    b = torso_like(300, 400, seed=6)
    with pytest.raises(ValueError, match="do not overlap"):
        icpatch(b, a)
