"""The vertebra prominens on the neck's flank of a sparse reconstruction: holes, noise, hair over the neck."""

import numpy as np

from analysis.backsurface import DepthMap
from analysis.landmarks import VP_MAX_STEP_MISFIT, VP_MIN_UPPER_FLANK, find_vp_crossing, point_on_midline


def flank(z, z0=1200.0, crest=80.0, hollow=40.0, s=40.0):
    """A neck's midline profile (mm): the kyphosis's crest below, the neck's hollow above, one step between."""
    return 0.5 * (crest + hollow) - 0.5 * (crest - hollow) * np.tanh((z - z0) / s)


def test_it_reads_the_vp_depth_through_a_hole_in_the_depth_map():
    x, z = np.arange(-60.0, 61.0, 2.0), np.arange(1100.0, 1301.0, 2.0)
    depth = np.repeat(flank(z)[:, None], len(x), axis=1)
    depth[(z > 1185) & (z < 1215)] = np.nan  # a hole across the whole midline at VP's height
    p = point_on_midline(DepthMap(x, z, depth), 1200.0, np.zeros(len(z)), z, below=True)
    # the skin at VP is 60 mm deep; 20 mm down the flank (where the read used to fall) it is 67.6 mm
    assert abs(p[1] - 60.0) < 1.0 and p[2] == 1200.0


def test_it_places_vp_at_the_flank_centre_despite_noise_and_gaps():
    rng = np.random.default_rng(7)
    zs = np.arange(1000.0, 1400.0, 4.0)
    found = []
    for _ in range(20):
        depth = flank(zs) + rng.normal(0.0, 0.4, len(zs))
        start = rng.uniform(1150.0, 1230.0)
        depth[(zs > start) & (zs < start + rng.uniform(10.0, 40.0))] = np.nan  # a hole somewhere on the flank
        z0, drop, misfit, _ = find_vp_crossing(zs, depth, 1190.0)
        assert misfit <= VP_MAX_STEP_MISFIT * drop
        found.append(z0)
    assert np.max(np.abs(np.subtract(found, 1200.0))) < 3.0
    assert np.std(found) < 1.5


def test_it_does_not_trust_a_neck_flank_of_two_steps():
    # hair over the neck, on a rendered re-scan: the back's own flank down to a plateau where the hair begins,
    # then a second step to the neck's hollow; one step's centre moved 74 mm between two same-day re-scans
    zs = np.arange(1000.0, 1400.0, 4.0)
    depth = (71.0 - 9.0 * np.tanh((zs - 1175.0) / 15.0) - 5.0 * np.tanh((zs - 1250.0) / 10.0)
             + 0.3 * np.clip(zs - 1290.0, 0.0, None) - 0.0004 * np.clip(1140.0 - zs, 0.0, None) ** 2)
    z0, drop, misfit, _ = find_vp_crossing(zs, depth, 1190.0)
    assert drop > 20 and misfit > VP_MAX_STEP_MISFIT * drop
    # the same drop in one step is trusted
    z0, drop, misfit, _ = find_vp_crossing(zs, flank(zs, 1200.0, 80.0, 52.0, 30.0), 1190.0)
    assert abs(z0 - 1200.0) < 0.5 and misfit < 0.01 * drop


def test_it_does_not_trust_a_flank_whose_top_the_scan_cut_off():
    # the kyphosis's crest below, one step, the neck's hollow, the back of the head rising above it
    def neck(z):
        return (70.0 - 14.0 * np.tanh((z - 1200.0) / 20.0) + 0.3 * np.clip(z - 1270.0, 0.0, None)
                - 0.0004 * np.clip(1150.0 - z, 0.0, None) ** 2)

    zs = np.arange(1000.0, 1400.0, 4.0)
    z0, drop, misfit, upper = find_vp_crossing(zs, neck(zs), 1190.0)
    assert upper >= VP_MIN_UPPER_FLANK and abs(z0 - 1200.0) < 1.0
    # a scan whose top stops just above the flank's centre: its lowest point is the scan's edge, not the neck's
    # hollow, and the step fitted below it is a guess
    zs = np.arange(1000.0, 1212.0, 4.0)
    z0, drop, misfit, upper = find_vp_crossing(zs, neck(zs), 1190.0)
    assert upper < VP_MIN_UPPER_FLANK
