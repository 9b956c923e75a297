"""The multiple registration leaves out narrower rims on a sharper rig: the matching's biases at the rims grow with
the mm of skin per pixel squared, and where they are small the rims hold the arms' rotation."""

from dataclasses import replace

import pytest

from recon_engine.registration import ICPatchConfig, rim_margins

from .test_registration_strength import four_arm_surfaces, register

PAIRS = [("A", "B"), ("B", "A")]


def test_the_margin_grows_with_the_skin_per_pixel_squared_up_to_its_cap():
    cfg = ICPatchConfig()
    sharp = rim_margins(PAIRS, cfg, {"A": 0.29, "B": 0.30})  # the paper rig: about 0.3 mm of skin per pixel
    assert sharp[("A", "B")] == pytest.approx(cfg.rim_margin_g2_mm * (0.29 ** 2 + 0.30 ** 2) / 2)
    assert 0.7 < sharp[("A", "B")] < 0.9
    coarse = rim_margins(PAIRS, cfg, {"A": 0.88, "B": 0.86})  # the cheaper rig, about 0.9 mm per pixel
    assert set(coarse.values()) == {cfg.rim_margin_mm}


def test_without_the_skin_per_pixel_or_its_rule_every_pair_keeps_the_fixed_margin():
    cfg = ICPatchConfig()
    assert set(rim_margins(PAIRS, cfg).values()) == {cfg.rim_margin_mm}
    fixed = replace(cfg, rim_margin_g2_mm=None)
    assert set(rim_margins(PAIRS, fixed, {"A": 0.3, "B": 0.3}).values()) == {cfg.rim_margin_mm}
    assert set(rim_margins(PAIRS, replace(cfg, rim_margin_mm=None), {"A": 0.3, "B": 0.3}).values()) == {None}


def test_a_sharper_rig_observes_the_pairs_nearer_the_rims_and_says_which_margins_it_used():
    surfaces, _ = four_arm_surfaces(smooth_c=False, noise=0.02)
    coarse = register(surfaces)["report"]["registration"]
    sharp = register(surfaces, principal_distance_px=5000.0)["report"]["registration"]  # ~0.3 mm per pixel
    assert set(coarse["rim_margins_mm"].values()) == {5.0}
    assert all(0.6 < m < 1.0 for m in sharp["rim_margins_mm"].values())
    assert all(0.25 < g < 0.35 for g in sharp["skin_per_pixel_mm"].values())
    for c, s in zip(coarse["pairs"], sharp["pairs"]):
        assert s["adjustment_pairs"] > c["adjustment_pairs"]  # the pairs within 5 mm of a rim, and beyond 1 mm
