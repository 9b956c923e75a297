"""Region of interest and Harris features."""

import numpy as np

from recon_engine.features import cell_features, harris_features, region_of_interest
from recon_engine.tracking import fill_cell_px
from recon_engine.formats import load_image, read_capture, read_rig


def _image(scenario, cam="A3"):
    rig = read_rig(scenario / "rig.json")
    return load_image(read_capture(scenario / "captures" / "visit0-a", rig), cam, rig)


def test_the_region_of_interest_is_the_lit_subject(torso_scenario):
    img = _image(torso_scenario)
    roi = region_of_interest(img)
    assert 0.05 < roi.mean() < 0.6
    # the dark background has no pattern: its brightest decile stays out
    assert np.percentile(img[roi], 50) > 3 * np.percentile(img[~roi], 50)


def test_a_user_polygon_narrows_the_region(torso_scenario):
    img = _image(torso_scenario)
    h, w = img.shape
    poly = np.array([[0, 0], [w // 2, 0], [w // 2, h], [0, h]])
    roi = region_of_interest(img, polygon=poly)
    assert not roi[:, w // 2 + 1:].any() and roi.any()


def test_harris_features_respect_the_region_and_the_spacing(torso_scenario):
    img = _image(torso_scenario)
    roi = region_of_interest(img)
    xy, resp = harris_features(img, roi, spacing=6)
    assert len(xy) > 100
    assert roi[np.round(xy[:, 1]).astype(int), np.round(xy[:, 0]).astype(int)].all()
    assert np.all(np.diff(resp) <= 0)  # strongest first
    d = np.abs(xy[:, None, :] - xy[None, :, :]).max(axis=2) + np.eye(len(xy)) * 1e9
    assert d.min() >= 2.0  # non-maximum suppression and one per cell
    sparse, _ = harris_features(img, roi, spacing=12)
    assert len(sparse) < 0.5 * len(xy)  # density is the spacing parameter


def test_an_image_without_texture_has_no_features():
    xy, _ = harris_features(np.full((50, 60), 128, np.uint8))
    assert xy.shape == (0, 2)


def test_cell_features_fill_the_cells_the_corners_left_empty(torso_scenario):
    img = _image(torso_scenario)
    roi = region_of_interest(img)
    corners, _ = harris_features(img, roi, spacing=6)
    fill = cell_features(img, roi, 4, taken=corners)
    assert len(fill) > len(corners)  # between a pattern's corners its dots' edges still carry texture
    cells = {tuple(c) for c in (fill // 4).astype(int)}
    assert len(cells) == len(fill)  # one point per cell at most
    assert not cells & {tuple(c) for c in (np.floor(corners) // 4).astype(int)}  # none where a corner is
    assert roi[fill[:, 1].astype(int), fill[:, 0].astype(int)].all()
    flat = np.full_like(img, 100)
    assert len(cell_features(flat, roi, 4)) == 0  # no texture, no point


def test_the_fill_starts_only_where_the_features_lie_farther_apart_on_the_skin_than_asked():
    class Pair:
        f = 2000.0  # px: at 2000 mm depth one pixel is 1 mm on the skin

    roi = np.ones((100, 100), bool)
    # 400 features on 10 000 px: 5 px, 5 mm apart
    assert fill_cell_px(Pair(), (1900.0, 2100.0), roi, 400, 2.0) == 2
    assert fill_cell_px(Pair(), (1900.0, 2100.0), roi, 400, 3.0) == 3
    assert fill_cell_px(Pair(), (1900.0, 2100.0), roi, 400, 6.0) == 0  # closer than asked already
    assert fill_cell_px(Pair(), lambda pair: (1900.0, 2100.0), roi, 400, 0.0) == 0  # off
    assert fill_cell_px(Pair(), (1900.0, 2100.0), roi, 400, 0.5) == 2  # never finer than 2 px


def _cells(seed=5):
    rng = np.random.default_rng(seed)
    cells = (rng.random((70, 100)) > 0.5).astype(np.float32) * 200 + 20
    return np.kron(cells, np.ones((3, 3), np.float32))  # a projected pattern of 3-px cells


def test_the_blur_estimate_orders_images_by_their_blur_and_leaves_them_unchanged():
    import cv2

    from recon_engine.features import blur_sigma

    pattern = _cells()
    images = [cv2.GaussianBlur(pattern, (0, 0), s) for s in (0.6, 0.9, 1.3, 1.8)]
    before = [im.copy() for im in images]
    blur = [blur_sigma(im) for im in images]
    assert np.all(np.diff(blur) > 0.05), blur
    assert all(np.array_equal(a, b) for a, b in zip(images, before))
    assert np.isnan(blur_sigma(np.full((50, 50), 90, np.uint8)))  # no edges: unknown, not sharp


def test_an_out_of_focus_pair_is_matched_with_the_larger_least_squares_windows():
    from recon_engine.matching import MatchingConfig, focus_adapted

    cfg = MatchingConfig()
    assert focus_adapted(cfg, cfg.blurred_above_px - 0.01) is cfg
    assert focus_adapted(cfg, float("nan")) is cfg
    blurred = focus_adapted(cfg, cfg.blurred_above_px + 0.01)
    assert (blurred.lsm_window, blurred.lsm_antialias_px) == (cfg.blurred_lsm_window, cfg.blurred_antialias_px)
    assert blurred.lsm_window > cfg.lsm_window and blurred.window == cfg.window


def test_the_corner_responses_in_strips_are_the_whole_images():
    """Harris and Shi-Tomasi computed strip by strip (bounded memory) match OpenCV's on the whole image."""
    import cv2

    from recon_engine import features

    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur((rng.random((3 * features.STRIP_ROWS + 37, 301)) * 255).astype(np.float32), (0, 0), 1.0)
    for fn, args in ((cv2.cornerHarris, (0.04,)), (cv2.cornerMinEigenVal, ())):
        whole = fn(img, 5, 3, *args)
        strips = features.corner_response_in_strips(fn, img, 5, 3, *args)
        assert strips.shape == whole.shape and strips.dtype == np.float32
        # the same neighbours everywhere, strip edges included: at most a rounding of the box filter's sums apart
        np.testing.assert_allclose(strips, whole, rtol=1e-5, atol=1e-6 * np.abs(whole).max())
    harris = features.corner_response_in_strips(cv2.cornerHarris, img, 5, 3, 0.04)
    assert np.array_equal(features.harris_response(img), harris)
