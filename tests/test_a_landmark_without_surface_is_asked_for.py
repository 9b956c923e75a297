"""A landmark whose height has no back surface on the midline (a hole in the reconstruction) is asked for.

A rendered re-scan's sacral point was found "with confidence" at a height where the reconstruction had no skin
on the midline: its position was empty and the indices rested on it.
"""

import numpy as np

import analysis.landmarks as landmarks
from analysis.indices import analyse_torso
from analysis.synthetic import synthetic_back


def test_it_asks_for_a_sacral_point_without_surface(monkeypatch):
    torso, _ = synthetic_back(rotation_deg=6.0, spacing_mm=3.5, noise_mm=0.05)
    assert analyse_torso(torso).report["landmarks"]["sacral_point"]["confidence"] == "high"
    real = landmarks.point_on_midline

    def hole_at_sp(dmap, z, xs=None, zs=None, cfg=None, below=False, x_hint=None):
        p = real(dmap, z, xs, zs, cfg, below, x_hint)
        return p if below else np.array([p[0], np.nan, p[2]])  # VP's call has below=True

    monkeypatch.setattr(landmarks, "point_on_midline", hole_at_sp)
    rep = analyse_torso(torso).report
    sp = rep["landmarks"]["sacral_point"]
    assert sp["confidence"] == "low" and "no surface on the midline" in sp["method"]
    assert "sacral_point" in rep["not_measurable"]["mark"]
    assert rep["surface_rotation_deg"]["max"] is None and rep["trunk_length_mm"] is None
