"""A landmark is placed by clicking on the torso picture: the pixel clicked is turned back into the skin point the
picture drew there (rig frame, mm)."""

import numpy as np
import pytest

from analysis.indices import analyse_torso
from analysis.pictures import pick_point, render_view
from analysis.synthetic import synthetic_back


@pytest.fixture(scope="module")
def back():
    torso, _ = synthetic_back(rotation_deg=6.0, lateral_mm=6.0, spacing_mm=5.0, noise_mm=0.05, seed=3)
    return torso, analyse_torso(torso)


def test_a_click_on_a_landmark_drawn_on_the_back_view_gives_that_landmark_back(back):
    torso, a = back
    # the projection torso_views draws the back view with (800 x 1000 px)
    r = render_view(torso, a.frame, "back")
    for name in ("vertebra_prominens", "sacral_point"):
        truth = np.asarray(a.landmarks[name], float)
        (x, y), = r.placement.project(truth)[0]
        picked = pick_point(torso, a.frame, "back", x, y)
        assert picked is not None, name
        (px, py), = r.placement.project(picked)[0]
        assert np.hypot(px - x, py - y) < 1.0, (name, (px, py), (x, y))  # the pixel clicked
        assert np.linalg.norm(picked - truth) < 3.0, (name, picked, truth)  # on the skin where the landmark is


def test_a_click_beside_the_torso_picks_nothing(back):
    torso, a = back
    assert pick_point(torso, a.frame, "back", 2.0, 2.0) is None


def test_it_refuses_a_view_it_does_not_draw(back):
    torso, a = back
    with pytest.raises(ValueError, match="view 'under'"):
        pick_point(torso, a.frame, "under", 400, 500)
