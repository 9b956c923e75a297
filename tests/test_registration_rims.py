"""The multiple registration weighted by the surfaces' precision, and the scale's a priori sigma."""

from functools import lru_cache

import numpy as np

from recon_engine.registration import ICPatchConfig
from recon_engine.surface import PointSurface

from .test_registration_strength import ARMS, four_arm_surfaces, register


def _with_imprecise_rims(surfaces, truth, bias_mm=0.15, rim_deg=50.0):
    """Each arm's points seen more than ``rim_deg`` off its viewing direction pushed ``bias_mm`` outwards along
    their normal and marked imprecise (0.3 mm along the normal against 0.02 mm elsewhere)."""
    out = {}
    for k, arm in enumerate(ARMS):
        s = surfaces[arm]
        body = truth[arm].apply(s.points)  # on the body, in the reference frame
        look = np.radians(90.0 * k)
        off = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(body[:, 2], body[:, 0]) - look)))))
        rim = off > rim_deg
        P = s.points + (bias_mm * rim)[:, None] * s.normals
        sig = np.where(rim, 0.3, 0.02).astype(np.float32)
        out[arm] = PointSurface(P, s.normals, s.faces, {**s.data, "sigma_normal_mm": sig})
    return out


@lru_cache(maxsize=None)
def _surfaces(biased=False):
    """The four arms' synthetic surfaces (with imprecise, biased rims if ``biased``) and the truth."""
    surfaces, truth = four_arm_surfaces(smooth_c=False, noise=0.02)
    return (_with_imprecise_rims(surfaces, truth) if biased else surfaces), truth


@lru_cache(maxsize=None)
def _registered(cfg, biased=False):
    """One registration per configuration, shared by the tests (each takes seconds; the tests only read it)."""
    return register(_surfaces(biased)[0], cfg)


def _position_errors(res, truth, surfaces):
    """RMS distance (mm) between where the registration and the truth put each arm's points."""
    out = {}
    for a in ARMS[1:]:
        x = surfaces[a].points
        out[a] = float(np.sqrt(np.mean(np.sum((res["transforms"][a].apply(x) - truth[a].apply(x)) ** 2, axis=1))))
    return out


def test_weighting_by_precision_discounts_the_imprecise_rims():
    biased, truth = _surfaces(biased=True)
    plain = _position_errors(_registered(ICPatchConfig(max_patch_edge=None), biased=True), truth, biased)
    weighted = _position_errors(_registered(ICPatchConfig(max_patch_edge=None, weighted=True), biased=True), truth,
                                biased)
    # the rims' bias moves the unweighted arms by 0.4-0.6 mm (0.10-0.14 mm without it: these sparse synthetic
    # surfaces hold the arms loosely); weighted, the precise cores hold them about twice as well
    assert min(plain.values()) > 0.3
    assert np.mean(list(weighted.values())) < 0.6 * np.mean(list(plain.values())), (plain, weighted)


def test_it_runs_unweighted_on_surfaces_without_normal_precision():
    res = _registered(ICPatchConfig(weighted=True))  # no sigma_normal_mm: every weight is 1
    ref = _registered(ICPatchConfig())
    for a in ARMS[1:]:
        assert np.allclose(res["transforms"][a].t, ref["transforms"][a].t, atol=1e-9)


def test_a_scale_prior_holds_each_arms_scale_near_one():
    free = _registered(ICPatchConfig(max_patch_edge=None, estimate_scale=True), biased=True)
    held = _registered(ICPatchConfig(max_patch_edge=None, estimate_scale=True, scale_sigma=1e-6), biased=True)
    for a in ARMS[1:]:
        assert abs(held["transforms"][a].scale - 1.0) < 2e-6
    # free, the rims' outward bias is partly taken up as scale
    assert max(abs(free["transforms"][a].scale - 1.0) for a in ARMS[1:]) > 1e-5


def test_a_negligible_pair_error_leaves_the_adjustment_as_it_was():
    plain = _registered(ICPatchConfig())
    tiny = _registered(ICPatchConfig(pair_sigma=(1e-12, 1e-12, 1e-10)))
    for a in ARMS[1:]:
        assert np.allclose(tiny["transforms"][a].t, plain["transforms"][a].t, atol=1e-4)


def test_each_pairs_systematic_error_shows_in_the_arms_sigmas():
    plain = _registered(ICPatchConfig())["report"]["registration"]["sigmas"]
    held = _registered(ICPatchConfig(pair_sigma=(2e-5, 3.5e-5, 0.01)))["report"]["registration"]["sigmas"]
    for a in ARMS[1:]:
        # arm C hangs on A through two pairs each side: its translation is no surer than a pair's 0.01 mm
        assert held[a]["tx_mm"] > plain[a]["tx_mm"]
        assert held[a]["tx_mm"] > 0.005


def test_the_point_normal_matrix_sums_each_points_displacement_jacobian():
    from recon_engine.registration import point_normal_matrix

    Y = np.random.default_rng(3).normal(0, 50, (40, 3))
    G = np.zeros((7, 7))
    for y in Y:
        # d(point) = ds * y + w x y + t
        J = np.column_stack([y, -np.array([[0, -y[2], y[1]], [y[2], 0, -y[0]], [-y[1], y[0], 0]]), np.eye(3)])
        G += J.T @ J
    assert np.allclose(point_normal_matrix(Y), G)


def test_a_stiff_pair_model_leaves_the_adjustment_as_it_was():
    plain = _registered(ICPatchConfig())
    stiff = _registered(ICPatchConfig(pair_stiffness=1e-14))
    for a in ARMS[1:]:
        assert np.allclose(stiff["transforms"][a].t, plain["transforms"][a].t, atol=1e-4)


def test_pairs_at_either_surfaces_rim_are_left_out():
    from recon_engine.registration import PatchIndex, correspondences

    surfaces, truth = _surfaces()
    a, b = surfaces["A"], surfaces["B"]
    fixed, own = PatchIndex(b), PatchIndex(a)
    rel = truth["B"].inverse().compose(truth["A"])
    cfg = ICPatchConfig(rim_margin_mm=15.0)
    every = correspondences(a.points, a.normals, fixed, rel, 2.0, cfg)  # no rim distances: pair-wise use
    kept = correspondences(a.points, a.normals, fixed, rel, 2.0, cfg, rim_distance=own.vertex_rim_distance)
    assert 0 < len(kept[0]) < len(every[0])
    assert own.vertex_rim_distance[kept[0]].min() >= 15.0
    assert fixed.rim_tree.query(kept[2])[0].min() >= 15.0


def test_table_1_counts_the_whole_overlap_whichever_pairs_the_adjustment_observed():
    plain = _registered(ICPatchConfig(rim_margin_mm=None))["report"]["registration"]["pairs"]
    rim = _registered(ICPatchConfig(rim_margin_mm=15.0))["report"]["registration"]["pairs"]
    for p, q in zip(plain, rim):
        assert (p["a"], p["b"]) == (q["a"], q["b"])
        # the adjustment left the rim pairs out...
        assert q["adjustment_pairs"] < 0.9 * p["adjustment_pairs"]
        # ...but the registered surfaces still fit over the whole overlap
        assert q["overlap_matched_fraction"] >= 0.95
        assert abs(q["overlap_matched_fraction"] - p["overlap_matched_fraction"]) < 0.02
        assert q["pairs"] > q["adjustment_pairs"]
