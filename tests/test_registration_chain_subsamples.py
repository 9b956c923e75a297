"""The pair-wise chain only starts the multiple registration: it registers a subsample of each moving arm
(``ICPatchConfig.chain_points``) and still places the arm as closely as with every point."""

import numpy as np

from recon_engine.bundle import rodrigues
from recon_engine import registration
from recon_engine.registration import ICPatchConfig, Transform, chain_initial
from tests.surface_pieces import moved, torso_like


def _rms(T, moving, part):
    return float(np.sqrt(np.mean(np.sum((T.apply(moving.points) - part.points) ** 2, axis=1))))


def test_it_registers_a_subsample_and_places_the_arm_as_well(monkeypatch):
    fixed = torso_like(-200, 100, n=12000, seed=21)
    part = torso_like(-50, 200, n=8000, seed=22, noise=0.05)
    truth = Transform(1.0, rodrigues(np.radians([0.3, -0.2, 0.5])), np.array([3.0, -2.0, 4.0]))
    moving = moved(part, truth.inverse())
    seen = []
    real = registration.icpatch

    def spy(moving_surface, *args, **kwargs):
        seen.append(len(moving_surface.points))
        return real(moving_surface, *args, **kwargs)

    monkeypatch.setattr(registration, "icpatch", spy)
    T_all, _ = chain_initial({"A": fixed, "B": moving}, ["A", "B"], "A", ICPatchConfig(chain_points=None))
    T_sub, res = chain_initial({"A": fixed, "B": moving}, ["A", "B"], "A", ICPatchConfig(chain_points=2000))
    assert seen == [8000, 2000]
    assert res[0]["a"] == "B"
    assert _rms(T_all["B"], moving, part) < 0.1
    assert _rms(T_sub["B"], moving, part) < 0.1
