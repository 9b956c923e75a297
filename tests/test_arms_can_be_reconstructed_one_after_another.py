"""A server short of memory reconstructs the arms one after the other in one process (``--arm-workers 1``):
the same torso as the arms in parallel processes."""

import numpy as np

from recon_engine.cli import main
from recon_engine.surface import read_ply


def reconstruct(scenario, out, *options):
    return main(["reconstruct", "--rig", str(scenario / "rig.json"),
                 "--calibration", str(scenario / "truth" / "calibration.json"), "--out", str(out), *options,
                 str(scenario / "captures" / "visit0-a")])


def test_one_after_another_gives_the_torso_of_parallel_arms(torso_scenario, tmp_path, capsys):
    assert reconstruct(torso_scenario, tmp_path / "parallel", "--arm-workers", "2") == 0
    assert "in 2 processes" in capsys.readouterr().out
    assert reconstruct(torso_scenario, tmp_path / "serial", "--arm-workers", "1") == 0
    assert "processes" not in capsys.readouterr().out
    a = read_ply(tmp_path / "parallel" / "torso.ply")["points"]
    b = read_ply(tmp_path / "serial" / "torso.ply")["points"]
    assert len(a) == len(b)
    assert np.abs(np.sort(a, axis=0) - np.sort(b, axis=0)).max() < 1e-3  # mm


def test_it_rejects_a_negative_number_of_arm_workers(torso_scenario, tmp_path, capsys):
    assert reconstruct(torso_scenario, tmp_path / "out", "--arm-workers", "-1") == 2
    assert "--arm-workers is -1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
