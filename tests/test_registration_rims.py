"""The multiple registration at the surfaces' rims, and each arm's scale (held at 1 unless estimated)."""

from functools import lru_cache

import numpy as np

from recon_engine.registration import ICPatchConfig
from recon_engine.surface import PointSurface

from .test_registration_strength import ARMS, four_arm_surfaces, register


def _with_biased_rims(surfaces, truth, bias_mm=0.15, rim_deg=50.0):
    """Each arm's points seen more than ``rim_deg`` off its viewing direction pushed ``bias_mm`` outwards along
    their normal."""
    out = {}
    for k, arm in enumerate(ARMS):
        s = surfaces[arm]
        body = truth[arm].apply(s.points)  # on the body, in the reference frame
        look = np.radians(90.0 * k)
        off = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(body[:, 2], body[:, 0]) - look)))))
        rim = off > rim_deg
        P = s.points + (bias_mm * rim)[:, None] * s.normals
        out[arm] = PointSurface(P, s.normals, s.faces, s.data)
    return out


@lru_cache(maxsize=None)
def _surfaces(biased=False):
    """The four arms' synthetic surfaces (with biased rims if ``biased``) and the truth."""
    surfaces, truth = four_arm_surfaces(smooth_c=False, noise=0.02)
    return (_with_biased_rims(surfaces, truth) if biased else surfaces), truth


@lru_cache(maxsize=None)
def _registered(cfg, biased=False):
    """One registration per configuration, shared by the tests (each takes seconds; the tests only read it)."""
    return register(_surfaces(biased)[0], cfg)


def test_each_arms_scale_is_held_at_one_unless_estimated():
    free = _registered(ICPatchConfig(max_patch_edge=None, estimate_scale=True), biased=True)
    held = _registered(ICPatchConfig(max_patch_edge=None), biased=True)
    for a in ARMS[1:]:
        assert abs(held["transforms"][a].scale - 1.0) < 1e-7  # held by a stiff weight, not exactly
    # free, the rims' outward bias is partly taken up as scale
    assert max(abs(free["transforms"][a].scale - 1.0) for a in ARMS[1:]) > 1e-5


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
