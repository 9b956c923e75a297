"""Off-screen pictures: each public function writes a non-empty PNG."""

import numpy as np
import pytest

from analysis.frame import frame_from_posterior
from analysis.synthetic import synthetic_back


@pytest.fixture(scope="module")
def torso():
    t, _ = synthetic_back(rotation_deg=8.0, spacing_mm=8.0)
    return t


def _png(path):
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    return path


def test_torso_views_and_maps(torso, tmp_path):
    from analysis import pictures

    frame = frame_from_posterior([0.0, 1.0, 0.0], np.median(torso.points, axis=0))
    paths = pictures.torso_views(torso, tmp_path, frame, size=(300, 400), views=("back", "top"))
    assert [p.split("/")[-1] for p in paths] == ["torso-back.png", "torso-top.png"]
    for p in paths:
        _png(p)
    d = torso.points[:, 1] * 0.01
    d[::7] = np.nan
    _png(pictures.deformation_picture(torso.points, d, tmp_path / "def.png", frame, size=(600, 400), mdc_mm=0.4,
                                      normals=torso.normals))
    _png(pictures.asymmetry_picture(torso, d, tmp_path / "asym.png", frame, size=(600, 400)))


def test_trend_picture(tmp_path):
    from datetime import date

    from analysis import pictures

    visits = [(date(2026, 1, 1), {"hump_mm": 5.0, "lateral_deviation_mm": {"rms": 3.0, "max": 6.0}}),
              (date(2026, 5, 1), {"hump_mm": 7.5, "lateral_deviation_mm": {"rms": 3.1, "max": 6.2}})]
    _png(pictures.trend_picture(visits, tmp_path / "trend.png", mdc={"hump_mm": 1.0}))
