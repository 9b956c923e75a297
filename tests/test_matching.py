"""NCC matching along the epipolar rows, with least-squares refinement."""

import cv2
import numpy as np
import pytest

from .truth import truth_scene
from recon_engine.camera import pixel_to_ray
from recon_engine.epipolar import rectify_pair, rig_centre, subject_depth_bounds
from recon_engine.features import harris_features, region_of_interest
from recon_engine.formats import load_image, read_calibration, read_capture, read_rig
from recon_engine.matching import MatchingConfig, least_squares_refine, match_points


@pytest.fixture(scope="module")
def pair_data(torso_scenario):
    from recon_engine.o3d import o3d

    rig = read_rig(torso_scenario / "rig.json")
    cal = read_calibration(torso_scenario / "truth" / "visit0-a" / "calibration.json")
    cap = read_capture(torso_scenario / "captures" / "visit0-a", rig)
    a, b = cal.cameras["A2"], cal.cameras["A3"]
    p = rectify_pair(a, b)
    left = p.resample("left", load_image(cap, "A2", rig).astype(np.float32))
    right = p.resample("right", load_image(cap, "A3", rig).astype(np.float32))
    xy, _ = harris_features(left, region_of_interest(left), spacing=4)
    dr = p.disparity_range(*subject_depth_bounds(p, rig_centre(list(cal.cameras.values())), 400))
    # truth: each left point's ray meets the body; its right image is the true match
    d = pixel_to_ray(a, p.to_original("left", xy))
    rays = np.column_stack([np.repeat(a.C[None], len(d), 0), d]).astype(np.float32)
    hit = truth_scene(torso_scenario).cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    X = a.C + d * hit[:, None]
    # hidden from the right camera: no true match
    to = X - b.C
    dist = np.linalg.norm(to, axis=1)
    rays_b = np.column_stack([np.repeat(b.C[None], len(d), 0), to / np.maximum(dist, 1e-9)[:, None]])
    rays_b = np.nan_to_num(rays_b).astype(np.float32)
    hit_b = truth_scene(torso_scenario).cast_rays(o3d.core.Tensor(rays_b))["t_hit"].numpy()
    true_r = p.to_rectified("right", b.project(X))
    true_r[~(np.abs(hit_b - dist) < 1.0)] = np.nan
    return p, left, right, xy, dr, true_r


def test_matches_land_on_the_true_conjugate_points(pair_data):
    p, left, right, xy, dr, true_r = pair_data
    m = match_points(left, right, xy, dr)
    v = m["valid"] & np.isfinite(true_r).all(axis=1)
    assert v.sum() > 0.35 * len(xy)
    err = np.linalg.norm(m["xy"][v] - true_r[v], axis=1)
    assert np.median(err) < 0.15 and np.mean(err > 2) < 0.005


def test_least_squares_matching_sharpens_the_correlation_peak(pair_data):
    p, left, right, xy, dr, true_r = pair_data
    m = match_points(left, right, xy, dr, MatchingConfig(refine=False))
    v = m["valid"] & np.isfinite(true_r).all(axis=1)
    lsm = least_squares_refine(left, right, xy[v], m["xy"][v], window=7)
    c = lsm["converged"]
    before = np.median(np.linalg.norm(m["xy"][v][c] - true_r[v][c], axis=1))
    after = np.median(np.linalg.norm(lsm["xy"][c] - true_r[v][c], axis=1))
    assert after < 0.7 * before


def test_matches_do_not_depend_on_how_the_points_are_split_into_blocks_and_threads(pair_data):
    p, left, right, xy, dr, true_r = pair_data
    one = match_points(left, right, xy, dr, MatchingConfig(threads=1))
    # the worker processes of a whole capture match on one thread each, a service's arm job on two
    other = match_points(left, right, xy, dr, MatchingConfig(threads=2, search_chunk=97, chunk=300))
    np.testing.assert_array_equal(one["xy"], other["xy"])
    np.testing.assert_array_equal(one["ncc"], other["ncc"])


def test_every_rejection_has_a_reason(pair_data):
    p, left, right, xy, dr, _ = pair_data
    m = match_points(left, right, xy, dr)
    assert set(m["reason"][~m["valid"]]) <= {
        "peak at the edge of the search range", "correlation below the minimum",
        "not unique (second peak too close)", "left-right check failed",
        "no reliable disparity in the neighbourhood", "least-squares matching failed"}
    assert np.all(m["reason"][m["valid"]] == "")


def test_a_shifted_copy_is_matched_at_the_shift():
    rng = np.random.default_rng(3)
    cells = (rng.random((60, 80)) > 0.5).astype(np.float32) * 200 + 20
    # a projected pattern of 3-px cells, slightly blurred like any optics
    left = cv2.GaussianBlur(np.kron(cells, np.ones((3, 3), np.float32)), (0, 0), 0.8)
    right = np.roll(left, -17, axis=1)
    xy = np.column_stack([rng.uniform(40, 200, 300), rng.uniform(20, 160, 300)])
    m = match_points(left, right, xy, (5, 40))
    v = m["valid"]
    assert v.mean() > 0.8
    assert np.allclose(m["xy"][v, 0], xy[v, 0] - 17, atol=0.01) and np.allclose(m["xy"][v, 1], xy[v, 1], atol=0.01)


def test_the_correlation_search_finds_the_peak_a_direct_computation_finds():
    from recon_engine.matching import ncc_search

    rng = np.random.default_rng(12)
    cells = (rng.random((60, 80)) > 0.5).astype(np.float32) * 200 + 20
    left = cv2.GaussianBlur(np.kron(cells, np.ones((3, 3), np.float32)), (0, 0), 0.8)
    right = np.roll(left, -11, axis=1) + rng.normal(0, 8, left.shape).astype(np.float32)
    xy = np.round(np.column_stack([rng.uniform(40, 200, 200), rng.uniform(20, 160, 200)]))
    x_pred = xy[:, 0] - 11 + rng.integers(-3, 4, 200)
    radius, band, window, h = 5, 1, 7, 3
    r = ncc_search(left, right, xy, x_pred, radius, band, window)
    # the reference: every window of the range correlated directly (whole pixels: no interpolation)
    for p in range(len(xy)):
        x, y = int(xy[p, 0]), int(xy[p, 1])
        t = left[y - h:y + h + 1, x - h:x + h + 1].astype(float).ravel()
        best, at = -2.0, None
        for dy in range(-band, band + 1):
            for dx in range(-radius, radius + 1):
                xr = int(x_pred[p]) + dx
                w = right[y + dy - h:y + dy + h + 1, xr - h:xr + h + 1].astype(float).ravel()
                c = np.corrcoef(t, w)[0, 1]
                if c > best:
                    best, at = c, (xr, y + dy)
        assert r["ncc"][p] == pytest.approx(best, abs=1e-6)
        assert np.all(np.abs(r["xy"][p] - at) <= 0.5)  # the subpixel fit stays within half a pixel of the peak


def _ramp_pair(gradient: float, integrate: bool = False):
    """A pattern and its right view whose disparity grows ever faster beyond column 100, reaching ``gradient``
    px/px at column 250: skin that turns away from the cameras.

    With ``integrate`` each right pixel averages the left image over its whole footprint, as a sensor does: the
    squeezed view loses the pattern's detail instead of aliasing it."""
    rng = np.random.default_rng(5)
    cells = (rng.random((70, 100)) > 0.5).astype(np.float32) * 200 + 20
    left = cv2.GaussianBlur(np.kron(cells, np.ones((3, 3), np.float32)), (0, 0), 0.8)
    h, w = left.shape

    def disparity(x):
        return 17.0 + gradient / 300.0 * np.maximum(x - 100.0, 0.0) ** 2

    # right column xr shows left column xl with xr = xl - d(xl): invert the monotonic map numerically
    xl_grid = np.linspace(0, w - 1, 20 * w)
    xr_of_xl = xl_grid - disparity(xl_grid)
    xr = np.arange(w, dtype=np.float64)
    xl = np.interp(xr, xr_of_xl, xl_grid, left=-100, right=-100)
    mapx = np.repeat(xl[None].astype(np.float32), h, axis=0)
    mapy = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    if not integrate:
        return left, cv2.remap(left, mapx, mapy, cv2.INTER_CUBIC, borderValue=0), disparity
    # the footprint of right pixel xr runs from xl(xr - 1/2) to xl(xr + 1/2): differences of the left rows'
    # running integral (16 samples per left pixel)
    fine = np.arange(0, w - 1, 1 / 16)
    rows = np.stack([np.interp(fine, np.arange(w), r) for r in left])
    integral = np.concatenate([np.zeros((h, 1)), np.cumsum(rows, axis=1) / 16], axis=1)
    edges = np.interp(np.arange(w + 1) - 0.5, xr_of_xl, xl_grid, left=-100, right=-100)
    pos = np.clip(edges * 16, 0, integral.shape[1] - 1)
    at = np.stack([np.interp(pos, np.arange(integral.shape[1]), r) for r in integral])
    width = np.diff(edges)
    right = np.where((edges[:-1] > 0) & (edges[1:] < w - 1), np.diff(at, axis=1) / np.maximum(width, 1e-9), 0)
    return left, right.astype(np.float32), disparity


def test_region_growing_follows_steep_skin():
    left, right, disparity = _ramp_pair(0.5)
    rng = np.random.default_rng(4)
    xy = np.column_stack([rng.uniform(20, 250, 1500), rng.uniform(20, 190, 1500)])
    steep = xy[:, 0] > 160  # the disparity changes by 0.2-0.5 px per px: the right window shrinks to 0.8-0.5
    # this ramp's right view is point-sampled (no pixel footprint): the template blur that assumes a sensor's
    # averaging would only misfit it
    without = match_points(left, right, xy, (5, 140), MatchingConfig(grow_passes=0, lsm_antialias_px=0.0))
    m = match_points(left, right, xy, (5, 140), MatchingConfig(lsm_antialias_px=0.0))
    assert m["valid"][steep].mean() > without["valid"][steep].mean() + 0.15
    grown = m["valid"] & ~without["valid"]
    err = np.abs(m["xy"][grown, 0] - (xy[grown, 0] - disparity(xy[grown, 0])))
    assert grown.sum() > 50 and np.median(err) < 0.05 and np.percentile(err, 95) < 0.2 and err.max() < 1.0
    assert np.all(np.abs(m["xy"][grown, 1] - xy[grown, 1]) < 0.2)


def test_growing_takes_each_points_nearest_matched_neighbours_within_its_radius():
    from scipy.spatial import cKDTree

    from recon_engine.matching import matched_neighbours

    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 200, (3000, 2))
    matched = rng.random(3000) < 0.4
    start = np.nonzero(matched & (rng.random(3000) < 0.7))[0]  # matched before growing
    since = np.setdiff1d(np.nonzero(matched)[0], start)  # matched by its rounds
    todo = np.nonzero(~matched)[0]
    cfg = MatchingConfig(grow_radius_px=9.0, neighbours=8)
    nb = matched_neighbours(cKDTree(xy[start]), start, since, xy, todo, cfg)
    # brute force: every matched point's distance, the nearest 8 within the radius, nearest first
    d = np.linalg.norm(xy[todo, None] - xy[None, matched], axis=2)
    ids = np.nonzero(matched)[0]
    order = np.argsort(d, axis=1, kind="stable")[:, :8]
    want = np.where(np.take_along_axis(d, order, axis=1) <= 9.0, ids[order], -1)
    assert (want == -1).any() and (want >= 0).all(axis=1).any()  # both cases occur
    assert np.array_equal(nb, want)


def test_stage_two_stretches_the_window_as_its_anchors_predict():
    left, right, disparity = _ramp_pair(0.3)
    rng = np.random.default_rng(4)
    xy = np.column_stack([rng.uniform(20, 250, 1500), rng.uniform(20, 190, 1500)])
    steep = xy[:, 0] > 160  # the right window shrinks to 0.88-0.7 of the left one there
    # one try per point and no growing: only the window's shape differs
    fixed = match_points(left, right, xy, (5, 140), MatchingConfig(grow_passes=0, predicted_shape=False, scales=()))
    m = match_points(left, right, xy, (5, 140), MatchingConfig(grow_passes=0, predicted_shape=True, scales=()))
    assert m["valid"][steep].mean() > fixed["valid"][steep].mean() + 0.03
    v = m["valid"]
    err = np.abs(m["xy"][v, 0] - (xy[v, 0] - disparity(xy[v, 0])))
    assert np.median(err) < 0.02 and err.max() < 0.5


def test_matching_samples_the_exact_bilinear_image():
    from recon_engine.kernels import bilinear

    rng = np.random.default_rng(8)
    img = rng.uniform(0, 255, (40, 50)).astype(np.float32)
    x = rng.uniform(-1, 50, 2000)
    y = rng.uniform(-1, 40, 2000)
    value = np.array([bilinear(img, a, b) for a, b in zip(x, y)])
    # the reference: bilinear interpolation in float64, pixels outside the image 0
    f = np.pad(img.astype(float), 1)  # one ring of zeros around the image
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    xi, yi = x0 + 1, y0 + 1
    ref = ((1 - fx) * (1 - fy) * f[yi, xi] + fx * (1 - fy) * f[yi, xi + 1] + (1 - fx) * fy * f[yi + 1, xi]
           + fx * fy * f[yi + 1, xi + 1])
    assert np.abs(value - ref).max() < 1e-3  # grey levels, not OpenCV's 1/32-px steps


def test_the_long_search_in_the_pyramid_finds_the_full_resolution_disparities():
    from dataclasses import replace

    from recon_engine.matching import seed_disparities

    rng = np.random.default_rng(6)
    cells = (rng.random((100, 300)) > 0.5).astype(np.float32) * 200 + 20
    # 2.5-px pattern cells as at paper scale; a range of 400 px either side as there
    left = cv2.GaussianBlur(cv2.resize(cells, (750, 250), interpolation=cv2.INTER_NEAREST), (0, 0), 0.8)
    right = np.roll(left, -310, axis=1) + rng.normal(0, 2, left.shape).astype(np.float32)
    xy = np.column_stack([rng.uniform(320, 730, 400), rng.uniform(10, 240, 400)])
    full_cfg = MatchingConfig(sparse_level=0)
    pyramid_cfg = replace(full_cfg, sparse_level=1, sparse_level_min_radius=150)
    seeds_full, d_full = seed_disparities(left, right, xy, 300.0, 400, full_cfg)
    seeds, d = seed_disparities(left, right, xy, 300.0, 400, pyramid_cfg)
    assert len(seeds_full) > 0.9 * len(xy) and len(seeds) > 0.97 * len(seeds_full)
    assert np.all(np.abs(d - 310) < 0.5) and np.median(np.abs(d - 310)) < 0.05
    # found again at full resolution: the same peaks as the full-resolution search's
    common, i, j = np.intersect1d(seeds[:, 0], seeds_full[:, 0], return_indices=True)
    assert len(common) == len(seeds) and np.allclose(d[i], d_full[j], atol=1e-4)
    # a short range stays at full resolution: the same seeds as without the pyramid
    short, d_short = seed_disparities(left, right, xy, 300.0, 100, pyramid_cfg)
    ref, d_ref = seed_disparities(left, right, xy, 300.0, 100, full_cfg)
    assert np.array_equal(short, ref) and np.array_equal(d_short, d_ref)


def test_growing_back_from_the_wider_view_reaches_skin_that_the_squeezed_template_misses():
    from recon_engine.matching import grow_matches

    # the ramp pair the other way round: the template image squeezes the steep skin (to a third of its width at the
    # far end), the other shows it whole
    wide, squeezed, disparity = _ramp_pair(0.65, integrate=True)
    rng = np.random.default_rng(4)
    xl = rng.uniform(20, 250, 1500)
    y = rng.uniform(20, 190, 1500)
    xy_sq = np.column_stack([xl - disparity(xl), y])  # the same skin points in the squeezed image
    forward = match_points(squeezed, wide, xy_sq, (-140, -5))
    v = forward["valid"]
    # the wide view's own points grow back from the matches into the squeezed image
    xy_wide = np.column_stack([rng.uniform(20, 250, 1500), rng.uniform(20, 190, 1500)])
    g = grow_matches(wide, squeezed, np.concatenate([forward["xy"][v], xy_wide]),
                     np.concatenate([xy_sq[v], np.full((len(xy_wide), 2), np.nan)]))
    assert np.allclose(g["xy"][:v.sum()], xy_sq[v]) and g["valid"][:v.sum()].all()  # known matches kept
    back = g["valid"][v.sum():]
    steep_fwd, steep_back = xl > 200, xy_wide[:, 0] > 200  # stretch 1.67-2 from the squeezed side
    # (measured with this session's defaults: 99% grown back against 85% matched forward, with 8 growing rounds or 4)
    assert back[steep_back].mean() > max(v[steep_fwd].mean() + 0.08, 0.93)
    err = np.abs(g["xy"][v.sum():][back, 0] - (xy_wide[back, 0] - disparity(xy_wide[back, 0])))
    assert np.median(err) < 0.05 and err.max() < 1.0


def test_the_template_blurred_to_a_squeezed_windows_detail_matches_it_more_often_and_closer():
    # least-squares matching started near the true match, on skin that the right view squeezes to 0.23-0.39 of
    # the template's width (each right pixel averages its footprint, as a sensor does)
    left, right, disparity = _ramp_pair(0.8, integrate=True)
    rng = np.random.default_rng(1)
    xl = rng.uniform(215, 245, 1500)
    xy = np.column_stack([xl, rng.uniform(20, 190, 1500)])
    d = disparity(xl)
    stretch = 1 - (disparity(xl + 1e-3) - disparity(xl - 1e-3)) / 2e-3
    assert 0.2 < stretch.min() and stretch.max() < 0.4
    true = np.column_stack([xl - d, xy[:, 1]])
    start = true + rng.normal(0, 0.3, true.shape)

    def refined(antialias_px):
        r = least_squares_refine(left, right, xy, start, window=9, initial_scale=stretch, antialias_px=antialias_px)
        good = r["converged"] & (r["rho"] >= 0.8) & (r["sigma"] <= 0.1)
        return good, np.abs(r["xy"][:, 0] - true[:, 0])

    plain, err_plain = refined(0.0)
    good, err = refined(0.6)  # the synthetic ramp has no light diffused in the skin: less blur than the default
    assert plain.mean() < 0.7 and good.mean() > 0.9
    assert np.percentile(err[good], 95) < 0.8 * np.percentile(err_plain[plain], 95) and err[good].max() < 0.5


def test_least_squares_matching_leaves_out_a_highlight_saturated_in_one_view():
    rng = np.random.default_rng(7)
    cells = (rng.random((60, 80)) > 0.5).astype(np.float32) * 150 + 40
    left = cv2.GaussianBlur(np.kron(cells, np.ones((3, 3), np.float32)), (0, 0), 0.8)
    right = cv2.warpAffine(left, np.float32([[1, 0, 10.4], [0, 1, 0]]), (left.shape[1], left.shape[0]))
    xy = np.column_stack([np.tile(np.arange(30, 211, 20), 8), np.repeat(np.arange(25, 166, 20), 10)]).astype(float)
    xy += rng.uniform(-3, 3, xy.shape)
    # beside every other point a highlight, clipped at 255, in the right view only (it moves with the view)
    hit = np.arange(len(xy)) % 2 == 0
    yy, xx = np.mgrid[:left.shape[0], :left.shape[1]]
    glare = sum(400 * np.exp(-((xx - (x + 12.9)) ** 2 + (yy - y) ** 2) / 4.5) for x, y in xy[hit])
    right = np.minimum(np.round(right + glare), 255).astype(np.float32)
    before = right.copy()
    plain = least_squares_refine(left, right, xy, xy + [10.7, 0.2], window=9)
    masked = least_squares_refine(left, right, xy, xy + [10.7, 0.2], window=9, clip=250.0)
    assert np.array_equal(right, before)

    def error(r, which):
        ok = r["converged"] & which
        return np.median(np.abs(r["xy"][ok, 0] - (xy[ok, 0] + 10.4))), ok.sum() / which.sum()

    (e_plain, c_plain), (e_masked, c_masked) = error(plain, hit), error(masked, hit)
    assert e_masked < 0.6 * e_plain and c_masked > c_plain
    # where nothing is saturated, nothing changes
    assert np.array_equal(plain["xy"][~hit], masked["xy"][~hit])
    assert np.array_equal(plain["sigma"][~hit], masked["sigma"][~hit])
