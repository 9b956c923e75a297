"""A reconstruction often leaves a narrow strip of holes along the spine (the depth map's cells on the line of
symmetry empty, the cells beside them full). Across the neck's flank such a strip cut the midline profile,
and VP, interpolated in height from 30 mm away, moved 6 mm between two same-day scans."""

import numpy as np

from analysis.backsurface import DepthMap, depth_across_gap
from analysis.config import IndicesConfig
from analysis.landmarks import VP_MAX_HOLE_MM, find_vp_crossing, marked_point, midline_profile, vp_flank_verdict


def neck_and_back(hole_rows=None, hole_cols=1):
    """A back whose midline rises from the neck's hollow (z 1200) down to the kyphosis's crest (z 1050), each
    row a symmetric bowl; ``hole_rows`` (z range, mm) emptied in ``hole_cols`` columns on the midline."""
    x = np.arange(-200.0, 201.0, 4.0)
    z = np.arange(900.0, 1300.0, 4.0)
    profile = 60.0 - 15.0 * (1 + np.tanh((z - 1120.0) / 25.0)) + 8.0 * np.exp(-0.5 * ((z - 1050.0) / 40.0) ** 2)
    profile = profile + np.where(z > 1190.0, 0.2 * (z - 1190.0), 0.0)  # back up towards the occiput
    depth = profile[:, None] - x[None, :] ** 2 / 800.0
    if hole_rows is not None:
        rows = (z >= hole_rows[0]) & (z <= hole_rows[1])
        mid = int(np.argmin(np.abs(x)))
        cols = slice(mid - (hole_cols - 1) // 2, mid + hole_cols // 2 + 1)
        depth[np.ix_(rows, np.arange(len(x))[cols])] = np.nan
    return DepthMap(x, z, depth)


def crossing(dmap):
    """The midline profile's heights and depths, and :func:`find_vp_crossing`'s figures on it."""
    zs, _, ds = midline_profile(dmap, IndicesConfig(grid_mm=4.0))
    return zs, ds, find_vp_crossing(zs, ds, 1100.0)


def vp_height(dmap):
    zs, ds, found = crossing(dmap)
    return found[0], zs, ds


def test_a_one_cell_strip_across_the_flank_leaves_vp_where_it_was():
    intact, _, _ = vp_height(neck_and_back())
    z_vp, zs, ds = vp_height(neck_and_back(hole_rows=(1080.0, 1140.0)))
    assert np.isfinite(ds[(zs > 1080) & (zs < 1140)]).all()
    assert abs(z_vp - intact) < 0.5


def test_a_wide_hole_is_not_bridged():
    # five cells (20 mm) across the line: no depth is made up there
    _, zs, ds = vp_height(neck_and_back(hole_rows=(1080.0, 1140.0), hole_cols=5))
    assert np.isnan(ds[(zs > 1084) & (zs < 1136)]).all()


def test_depth_across_gap_reads_between_the_nearest_values():
    x = np.arange(0.0, 50.0, 5.0)
    row = 2.0 * x
    row[4] = np.nan
    assert depth_across_gap(x, row, 20.0, 10.0) == 40.0  # linear between 15 and 25
    assert depth_across_gap(x, row, 15.0, 10.0) == 30.0
    assert np.isnan(depth_across_gap(x, row, 20.0, 5.0))  # the hole is wider than allowed
    assert np.isnan(depth_across_gap(x, row, -1.0, 10.0)) and np.isnan(depth_across_gap(x, row, 46.0, 10.0))


def test_vp_interpolated_across_a_wide_hole_says_so():
    assert crossing(neck_and_back())[2][3] <= VP_MAX_HOLE_MM
    found = crossing(neck_and_back(hole_rows=(1080.0, 1140.0), hole_cols=5))[2]
    assert found[3] > VP_MAX_HOLE_MM
    assert vp_flank_verdict(*found[1:]) == ("low", "neck flank, not seen at its height: a hole in the scan there")


def test_a_neck_hollow_is_trusted_and_a_narrow_dip_is_not():
    # the intact neck's hollow is broad; a dip 12 mm tall and 25 mm deep above the flank (hair, a fold) is not
    _, _, neck = crossing(neck_and_back())
    assert vp_flank_verdict(*neck[1:]) == ("high", "neck flank")
    dmap = neck_and_back()
    dip = 25.0 * np.exp(-0.5 * ((dmap.z - 1180.0) / 5.0) ** 2)
    dmap = DepthMap(dmap.x, dmap.z, dmap.depth - dip[:, None])
    _, _, found = crossing(dmap)
    assert found[4] < neck[4]
    assert vp_flank_verdict(*found[1:])[0] == "low" and "too narrow" in vp_flank_verdict(*found[1:])[1]


def test_a_mark_beside_a_strip_of_holes_sits_on_the_map_not_at_the_clicks_depth():
    # the clinician clicks VP on the displayed mesh, 1.5 mm off the map's surface, where one cell is missing
    dmap = neck_and_back(hole_rows=(1080.0, 1140.0))
    on_map = neck_and_back().at(0.0, 1110.0)
    placed = marked_point(dmap, np.array([0.0, on_map + 1.5, 1110.0]))
    assert abs(placed[1] - on_map) < 0.05
    # beyond the map (no depth within a midline's hole) the click's own depth is kept
    wide = neck_and_back(hole_rows=(1080.0, 1140.0), hole_cols=5)
    assert marked_point(wide, np.array([0.0, 42.0, 1110.0]))[1] == 42.0
