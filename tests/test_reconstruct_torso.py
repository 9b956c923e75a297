"""The whole torso: four arms, ICPatch pair-wise and all together, fused (tiny preset)."""

import json

import numpy as np
import open3d as o3d
import pytest

from recon_engine.cli import main
from recon_engine.surface import read_ply

from .truth import truth_scene


@pytest.fixture(scope="module")
def torso_out(torso_scenario, tmp_path_factory):
    out = tmp_path_factory.mktemp("recon") / "visit0-a"
    rc = main(["reconstruct", "--rig", str(torso_scenario / "rig.json"),
               "--calibration", str(torso_scenario / "truth" / "calibration.json"),
               "--out", str(out), str(torso_scenario / "captures" / "visit0-a")])
    assert rc == 0
    return out


def test_the_displaced_arms_come_together_on_the_true_body(torso_scenario, torso_out):
    pts = read_ply(torso_out / "torso.ply")["points"]
    d = truth_scene(torso_scenario).compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    # tiny images (2.1 mm pixels); without registration the arms sit up to ~12 mm off
    assert np.sqrt(np.mean(d ** 2)) < 0.8 and np.percentile(d, 95) < 1.6


def test_the_report_holds_every_neighbouring_pair_including_the_closing_one(torso_out):
    rep = json.loads((torso_out / "report.json").read_text())
    assert rep["format"] == "torso-reconstruction/1" and rep["points"] > 2000
    pairs = {(p["a"], p["b"]) for p in rep["registration"]["pairs"]}
    assert pairs == {("A", "B"), ("B", "C"), ("C", "D"), ("D", "A")}
    for p in rep["registration"]["pairs"]:
        assert 0 < p["average_normal_distance_mm"] < 1.0 and 0 < p["matched_fraction"] <= 1


def test_overlaps_are_fused_and_a_display_mesh_is_written(torso_out):
    rep = json.loads((torso_out / "report.json").read_text())
    assert rep["points"] < rep["fused_from"]
    mesh = read_ply(torso_out / "torso-mesh.ply")
    assert len(mesh["faces"]) > 1000


def test_it_refuses_to_write_over_an_earlier_result(torso_scenario, torso_out, capsys):
    rc = main(["reconstruct", "--rig", str(torso_scenario / "rig.json"),
               "--calibration", str(torso_scenario / "truth" / "calibration.json"),
               "--out", str(torso_out), str(torso_scenario / "captures" / "visit0-a")])
    assert rc == 2 and "already exists" in capsys.readouterr().err
