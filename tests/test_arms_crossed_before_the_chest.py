"""Forearms crossed in front of the chest: the back's midline is not pulled by them, and a surface rotation
whose apex cannot be read is withheld with the levels and why, not replaced by another level's value."""

from dataclasses import replace

import numpy as np
import pytest

from analysis.backsurface import depth_map
from analysis.config import IndicesConfig
from analysis.indices import analyse_torso, fill_between, unread_apex_levels, unread_runs
from analysis.synthetic import scan_surface
from recon_engine.simulator.config import SubjectConfig, preset
from recon_engine.simulator.posed import posed_subject, posture_like


def test_skin_far_in_front_of_the_back_does_not_enter_its_depth_map():
    # a flat back at y = 100 mm sampled every 3 mm (most 2 mm cells empty), and in front of it, at y = -150 mm,
    # a forearm's side whose normals lean backwards (60 deg from posterior: within the back's 80)
    rng = np.random.default_rng(0)
    x, z = np.meshgrid(np.arange(-100, 100, 3.0), np.arange(1000, 1200, 3.0))
    back = np.column_stack([x.ravel(), np.full(x.size, 100.0), z.ravel()])
    fx, fz = rng.uniform(-100, 100, 4000), rng.uniform(1080, 1120, 4000)
    fore = np.column_stack([fx, np.full(fx.size, -150.0), fz])
    P = np.vstack([back, fore])
    N = np.vstack([np.tile([0.0, 1.0, 0.0], (len(back), 1)),
                   np.tile([np.sin(np.radians(60)), np.cos(np.radians(60)), 0.0], (len(fore), 1))])
    dmap = depth_map(P, N, IndicesConfig())
    row = dmap.row(1100.0)
    mid = np.abs(dmap.x) < 80
    assert np.nanmax(np.abs(row[mid] - 100.0)) < 0.5


def test_the_back_s_own_steep_flank_stays_in_its_depth_map():
    # a back turning away at 75 deg (within back_normal_deg): its cells keep their own depth
    x, z = np.meshgrid(np.arange(0, 60, 1.0), np.arange(1000, 1100, 2.0))
    slope = np.tan(np.radians(75.0))
    y = 100.0 - slope * np.clip(x - 20.0, 0, None)
    P = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    n = np.column_stack([np.where(x.ravel() > 20, np.sin(np.radians(75)), 0.0), np.where(x.ravel() > 20, np.cos(np.radians(75)), 1.0),
                         np.zeros(x.size)])
    dmap = depth_map(P, n, IndicesConfig())
    row = dmap.row(1050.0)
    at = (dmap.x > 30) & (dmap.x < 50)
    expected = 100.0 - slope * (dmap.x[at] - 20.0)
    assert np.all(np.isfinite(row[at]))
    assert np.nanmax(np.abs(row[at] - expected)) < 8.0


def _sections(rot, mid):
    return [{"level": 0.05 + 0.025 * k, "surface_rotation_deg": r, "midline_rotation_deg": m}
            for k, (r, m) in enumerate(zip(rot, mid))]


def test_it_names_the_unread_run_that_holds_an_apex():
    nan = float("nan")
    mid = [1, 3, 6, 9, 12, 9, 6, 3, 1, -2, -5, -3]
    rot = [1, 3, 6, nan, nan, nan, 6, 3, 1, -2, -5, -3]
    assert unread_apex_levels(_sections(rot, mid)) == [(0.125, 0.175)]
    # a short run beside well-read neighbours (a large rotation's most turned section) is not withheld
    assert unread_apex_levels(_sections(rot, mid), min_span=0.1) == []
    assert unread_apex_levels(_sections([1, nan, nan, nan, nan, nan, 6, 3, 1, -2, -5, -3], mid),
                              min_span=0.1) == [pytest.approx((0.075, 0.175))]
    # the apex read, unread sections elsewhere: nothing to withhold
    rot = [1, 3, 6, 9, 12, 9, nan, nan, 1, -2, -5, -3]
    assert unread_apex_levels(_sections(rot, mid)) == []
    # a side whose midline leans less than 2 deg has no apex to miss
    rot = [1, 3, 6, 9, 12, 9, 6, 3, 1, nan, nan, nan]
    assert unread_apex_levels(_sections(rot, [*mid[:9], -0.5, -1.5, -1.0])) == []


# the held-out body (bench_bodies.py, seed 200, body 1) whose +10 deg visit, its forearms crossed, read its
# surface rotation 16.6 deg to the left: its lumbar curve, the right thoracic apex (21.8 deg) unread
HEAVY_BOY = dict(stature_mm=1682.0, build_width=1.11, build_depth=1.22, belly_mm=22.3, curve="S", thoracic_apex=0.64,
                 dimples_mm=1.5)


@pytest.mark.parametrize("crossed", [False, True])
def test_a_scan_with_the_arms_across_the_chest_withholds_the_surface_rotation(crossed):
    base = preset("paper")
    cfg = replace(base, subject=replace(SubjectConfig(), arms_crossed=crossed, **HEAVY_BOY))
    s = posed_subject(cfg, posture=posture_like(cfg, 21.8, 34.9))
    z = s["vertices"][s["triangles"]].mean(axis=1)[:, 2]
    lm = s["landmarks"]
    region = (z > lm["sacral_point"][2] - 150.0) & (z < lm["vertebra_prominens"][2] + 160.0)
    rep = analyse_torso(scan_surface(s["vertices"], s["triangles"], region, n_points=80_000, seed=5)).report
    # the back's midline is read the same either way: its skin rotation at the thoracic apex is the curve's
    mid = [x["midline_rotation_deg"] for x in rep["sections"] if 0.55 <= x["level"] <= 0.75]
    assert max(mid) > 15.0
    if crossed:
        assert rep["surface_rotation_deg"]["max"] is None and rep["surface_rotation_deg"]["right"] is None
        assert "surface_rotation_deg" in rep["not_measurable"]["indices"]
        assert "arms held across the chest" in rep["not_measurable"]["reason"]
        assert all(r["surface_rotation_deg"]["max"] is None for r in rep["regions"].values())
        # the spine midline turns a short run of unread sections by the rotation interpolated from the read
        # sections at its ends, and the long run across the apex by the midline skin's (a straight line would cut
        # the curve's peak off)
        secs = rep["sections"]
        rot = np.array([x["surface_rotation_unsmoothed_deg"] for x in secs])
        levels = np.array([x["level"] for x in secs])
        turn = fill_between([x["z_mm"] for x in secs], rot)
        mid = np.array([x["midline_rotation_unsmoothed_deg"] for x in secs])
        runs = [(lo, hi) for lo, hi in unread_runs(rot) if 0 < lo and hi < len(rot) - 1]
        long = [(lo, hi) for lo, hi in runs if levels[hi] - levels[lo] >= IndicesConfig().unread_apex_min_span]
        assert long, "the forearms hide the apex's sections"
        expected = turn.copy()
        for lo, hi in long:
            expected[lo:hi + 1] = mid[lo:hi + 1]
        inner = np.zeros(len(rot), bool)
        for lo, hi in runs:
            inner[lo:hi + 1] = True
        spine = np.array([x["spine_lateral_deviation_mm"] for x in secs])
        lateral = np.array([x["lateral_deviation_mm"] for x in secs])
        depth = IndicesConfig().spine_depth_mm
        assert np.allclose(spine[inner], lateral[inner] + depth * np.sin(np.radians(expected[inner])), atol=1e-6)
        # and the long run's rotation is not the straight line's, which reads the apex lower
        lo, hi = long[0]
        assert np.max(mid[lo:hi + 1] - turn[lo:hi + 1]) > 2.0
    else:
        assert rep["surface_rotation_deg"]["right"]["size"] > 18.0
        assert "surface_rotation_deg" not in (rep.get("not_measurable") or {}).get("indices", [])
