"""The rigid registration stops once its iterations come back to an earlier pose (its pair sets cycling), where it
would otherwise repeat the cycle up to its last iteration: the same pose, a fraction of the time."""

from dataclasses import replace

import numpy as np

import analysis.frame
from analysis.indices import analyse_torso
from analysis.rigid import register_rigid, rotation_angle_deg
from analysis.synthetic import synthetic_back


def test_it_stops_in_a_cycle_at_the_pose_the_full_run_ends_in(monkeypatch):
    calls = []

    def recorded(*args, **kwargs):
        calls.append((args, kwargs, register_rigid(*args, **kwargs)))
        return calls[-1][2]

    # the mirror registrations of one synthetic back's analysis: on this back one of three cycles (measured)
    monkeypatch.setattr(analysis.frame, "register_rigid", recorded)
    torso, _ = synthetic_back(rotation_deg=5, lateral_mm=5, spacing_mm=5.0, noise_mm=0.05, seed=0)
    analyse_torso(torso)
    cycled = [(a, kw, r) for a, kw, r in calls if r["cycle"]]
    assert cycled, [(r["iterations"], r["converged"]) for _, _, r in calls]
    args, kwargs, stopped = cycled[0]
    cfg = args[2]
    assert not stopped["converged"] and 2 <= stopped["cycle"] <= cfg.cycle_max
    assert stopped["iterations"] < cfg.max_iterations
    # the same registration, never stopped at a cycle: it runs on, and ends where the stopped one did
    full = register_rigid(args[0], args[1], replace(cfg, cycle_max=0), *args[3:], **kwargs)
    assert full["cycle"] == 0 and full["iterations"] > stopped["iterations"]
    assert rotation_angle_deg(full["R"] @ stopped["R"].T) < 0.01
    assert np.linalg.norm(full["t"] - stopped["t"]) < 0.02
