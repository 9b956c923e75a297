"""Region of interest and Harris features."""

import numpy as np

from recon_engine.features import harris_features, region_of_interest
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
