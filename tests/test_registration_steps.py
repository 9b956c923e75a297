"""The multiple registration's named steps on small known cases (the whole is tested in test_registration_*)."""

import numpy as np

from recon_engine.bundle import rodrigues
from recon_engine.registration import (ICPatchConfig, Transform, apply_corrections, linked_arms, normal_equations,
                                       observed_pairs, pair_residuals, tightened_distances)


def test_pairs_are_observed_both_ways_round_the_circle():
    assert observed_pairs(["A", "B", "C"], symmetric=False) == [("A", "B"), ("B", "C"), ("C", "A")]
    assert observed_pairs(["A", "B", "C"])[3:] == [("B", "A"), ("C", "B"), ("A", "C")]


def test_an_arm_no_held_pair_reaches_is_not_linked():
    assert linked_arms([("B", "A"), ("C", "B")], "A") == {"A", "B", "C"}
    assert linked_arms([("B", "A"), ("D", "C")], "A") == {"A", "B"}


def test_a_translated_arm_is_moved_back_by_one_gauss_newton_step():
    # arm B's points lie on A's plane z = 0, but B is placed 0.3 mm too high and 0.2 mm aside (along the plane)
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-50, 50, (200, 2)), np.zeros(200)])
    n_loc = np.tile([0.0, 0.0, 1.0], (200, 1))
    T = {"A": Transform.identity(), "B": Transform(1.0, np.eye(3), np.array([0.2, 0.0, 0.3]))}
    x, foot, n, d = pair_residuals(X, n_loc, X * [1, 1, 0], T["B"], T["A"])
    assert np.allclose(d, 0.3) and np.allclose(foot[:, 2], 0.0)
    col, centres = {"B": 0}, {"B": x.mean(axis=0)}
    N, rhs = normal_equations({("B", "A"): (x, foot, n, d)}, col, centres, 7, 1e12)
    # the plane holds B along z and in tilt only: the rest is left to a small damping (as the caller's other pairs)
    dx = np.linalg.solve(N + 1e-9 * np.eye(7), rhs)
    T2, biggest = apply_corrections(T, dx, col, centres, ICPatchConfig())
    assert abs(T2["B"].t[2]) < 1e-9 and abs(T2["B"].t[0] - 0.2) < 1e-6  # along the plane: nothing observed
    assert biggest > 1.0 and T2["A"] is T["A"]
    # a rotation about the centre leaves the centre in place
    T3, _ = apply_corrections(T, np.r_[0.0, 0.01, 0.0, 0.0, 0, 0, 0], col, centres, ICPatchConfig())
    assert np.allclose(T3["B"].apply(X.mean(axis=0)), T["B"].apply(X.mean(axis=0)))
    assert np.allclose(T3["B"].R, rodrigues(np.array([0.01, 0.0, 0.0])))


def test_acceptance_distances_only_tighten():
    cfg = ICPatchConfig(tighten_k=4.0, min_distance_mm=0.5)
    dist = {"p": 2.0, "q": 2.0, "r": 2.0}
    out = tightened_distances(dist, {"p": np.full(10, 0.2), "q": np.full(10, 1.0), "r": np.zeros(0)}, cfg)
    assert abs(out["p"] - 0.8) < 1e-12 and out["q"] == 2.0 and out["r"] == 2.0 and dist["p"] == 2.0
    assert tightened_distances(dist, {"p": np.full(10, 0.01)}, cfg)["p"] == 0.5
