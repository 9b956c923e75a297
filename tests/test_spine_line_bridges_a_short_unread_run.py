"""Sections beside an arm hanging against the flank cannot be read; the spine line turns a short run of them by
the rotation interpolated from the read sections at its ends, not by the midline skin's, which reads more."""

from dataclasses import replace

import numpy as np

from analysis.config import IndicesConfig
from analysis.indices import analyse_torso, fill_between, unread_runs
from analysis.synthetic import scan_surface
from recon_engine.simulator.config import SubjectConfig, preset
from recon_engine.simulator.posed import posed_subject, posture_like

# held-out seed 300's body 7 (bench_bodies.py): a broad girl whose arms hang against her flanks
BROAD_GIRL = dict(stature_mm=1785.3, build_width=1.219, build_depth=1.267, belly_mm=13.6, breasts_mm=18.6, hips=1.035,
                  arm_abduction_deg=0.64, curve="S", thoracic_apex=0.663, dimples_mm=2.0)


def test_a_short_unread_run_takes_the_interpolated_rotation():
    base = preset("paper")
    cfg = replace(base, subject=replace(SubjectConfig(), **BROAD_GIRL))
    s = posed_subject(cfg, posture=posture_like(cfg, 10.36, 16.58))
    z = s["vertices"][s["triangles"]].mean(axis=1)[:, 2]
    lm = s["landmarks"]
    region = (z > lm["sacral_point"][2] - 150.0) & (z < lm["vertebra_prominens"][2] + 72.0)
    secs = analyse_torso(scan_surface(s["vertices"], s["triangles"], region, n_points=80_000, seed=5)).report["sections"]
    rot = np.array([x["surface_rotation_unsmoothed_deg"] for x in secs])
    levels = np.array([x["level"] for x in secs])
    ic = IndicesConfig()
    short = [(lo, hi) for lo, hi in unread_runs(rot)
             if 0 < lo and hi < len(rot) - 1 and levels[hi] - levels[lo] < ic.unread_apex_min_span]
    assert short, "the arms against the flanks leave a short run of unread sections"
    turn = fill_between([x["z_mm"] for x in secs], rot)
    mid = np.array([x["midline_rotation_unsmoothed_deg"] for x in secs])
    spine = np.array([x["spine_lateral_deviation_mm"] for x in secs])
    lateral = np.array([x["lateral_deviation_mm"] for x in secs])
    at = np.concatenate([np.arange(lo, hi + 1) for lo, hi in short])
    assert np.allclose(spine[at], lateral[at] + ic.spine_depth_mm * np.sin(np.radians(turn[at])), atol=1e-6)
    assert np.max(np.abs(mid[at] - turn[at])) > 1.0  # the midline skin's would have moved the line
