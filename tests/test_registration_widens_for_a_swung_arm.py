"""An arm that swung further than the registration's start distance (1 deg about a pivot 2.5 m away moves the
skin by about 40 mm) is still placed: the start distance is widened for it, not the torso failed."""

import numpy as np

from recon_engine.bundle import rodrigues
from recon_engine.registration import ICPatchConfig, Transform, chain_initial
from tests.surface_pieces import moved, torso_like


def test_it_places_an_arm_displaced_beyond_the_start_distance():
    fixed = torso_like(-200, 100, n=12000, seed=11)
    part = torso_like(-50, 200, n=6000, seed=12, noise=0.05)
    cfg = ICPatchConfig()
    truth = Transform(1.0, rodrigues(np.radians([0.0, 0.0, 0.9])), np.array([-12.0, 8.0, 45.0]))
    assert truth.t[2] > 1.5 * cfg.initial_distance_mm  # along the skin's normal: no pair within the start distance
    moving = moved(part, truth.inverse())  # where the arm's own calibration put what it saw
    T, results = chain_initial({"A": fixed, "C": moving}, ["A", "C"], "A", cfg)
    assert "C" in T and results[0]["a"] == "C"
    err = T["C"].apply(moving.points) - part.points
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.1


def test_surfaces_that_never_overlap_are_still_left_unplaced():
    a = torso_like(-200, -100, seed=13)
    b = torso_like(300, 400, seed=14)
    T, results = chain_initial({"A": a, "B": b}, ["A", "B"], "A", ICPatchConfig())
    assert "B" not in T and results == []


def test_a_pair_too_sparse_at_the_start_distance_is_tried_again_wider(monkeypatch):
    """The sampled overlap count can promise pairs that ICPatch then does not find within the start distance
    (seed 31 at paper scale: 2 pairs within 25 mm): the arm is placed from a wider start, not the torso failed."""
    from recon_engine import registration

    fixed = torso_like(-200, 100, n=12000, seed=11)
    part = torso_like(-50, 200, n=6000, seed=12, noise=0.05)
    truth = Transform(1.0, rodrigues(np.radians([0.0, 0.0, 0.5])), np.array([-6.0, 4.0, 10.0]))
    moving = moved(part, truth.inverse())
    cfg = ICPatchConfig()
    real = registration.icpatch
    starts = []

    def sparse_at_the_start(moving, fixed, initial=None, cfg=None, index=None):
        starts.append(cfg.initial_distance_mm)
        if cfg.initial_distance_mm <= ICPatchConfig().initial_distance_mm:
            raise registration.TooFewPairs("ICPatch: only 2 point-patch pairs within 25.0 mm")
        return real(moving, fixed, initial, cfg, index)

    monkeypatch.setattr(registration, "icpatch", sparse_at_the_start)
    T, results = chain_initial({"A": fixed, "C": moving}, ["A", "C"], "A", cfg)
    assert starts == [cfg.initial_distance_mm, 2 * cfg.initial_distance_mm]
    err = T["C"].apply(moving.points) - part.points
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.1
