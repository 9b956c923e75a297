"""torsoscan compare and indices: files written, keys of the spec, exit codes on bad input."""

import json

import numpy as np
import pytest

from analysis.cli import main
from analysis.synthetic import synthetic_back
from recon_engine.surface import read_ply, write_ply


@pytest.fixture(scope="module")
def plys(tmp_path_factory):
    d = tmp_path_factory.mktemp("torsos")
    a, _ = synthetic_back(rotation_deg=8.0, spacing_mm=4.5, noise_mm=0.05, seed=5)
    b, _ = synthetic_back(rotation_deg=8.0, spacing_mm=4.5, noise_mm=0.05, seed=6)
    write_ply(d / "a.ply", a.points, a.normals)
    write_ply(d / "b.ply", b.points + [3.0, 2.0, 1.0])
    return d


def test_indices_command(plys, tmp_path, capsys):
    out = tmp_path / "indices.json"
    assert main(["indices", "--out", str(out), str(plys / "a.ply")]) == 0
    rep = json.loads(out.read_text())
    assert rep["format"] == "torso-indices/1"
    for k in ("lateral_deviation_mm", "surface_rotation_deg"):
        assert set(rep[k]) >= {"rms", "max"}
    for k in ("hump_mm", "trunk_imbalance_mm", "asymmetry_mm"):
        assert isinstance(rep[k], float)
    assert rep["surface_rotation_deg"]["max"] > 5


def test_compare_command(plys, tmp_path):
    assert main(["compare", "--out", str(tmp_path / "cmp"), str(plys / "a.ply"), str(plys / "b.ply")]) == 0
    rep = json.loads((tmp_path / "cmp" / "report.json").read_text())
    assert rep["format"] == "torso-comparison/1"
    for k in ("average_normal_distance_mm", "matched_fraction"):
        assert isinstance(rep[k], float)
    assert set(rep["signed_distance_mm"]) >= {"mean", "p05", "p95"}
    assert np.array(rep["transform"]["R"]).shape == (3, 3) and len(rep["transform"]["t"]) == 3
    assert np.allclose(rep["transform"]["t"], [-3.0, -2.0, -1.0], atol=0.5)
    ply = read_ply(tmp_path / "cmp" / "deformation.ply")
    assert "deformation_mm" in ply["data"]


def test_missing_file(tmp_path, capsys):
    missing = tmp_path / "nope.ply"
    assert main(["indices", "--out", str(tmp_path / "i.json"), str(missing)]) != 0
    err = capsys.readouterr().err
    assert str(missing) in err and "no such file" in err


def test_not_a_ply(plys, tmp_path, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_text("this is not a point cloud\n")
    assert main(["compare", "--out", str(tmp_path / "c"), str(bad), str(plys / "a.ply")]) != 0
    err = capsys.readouterr().err
    assert str(bad) in err and "PLY" in err


def test_too_few_points(tmp_path, capsys):
    small = tmp_path / "small.ply"
    write_ply(small, np.random.default_rng(0).normal(size=(50, 3)))
    assert main(["indices", "--out", str(tmp_path / "i.json"), str(small)]) != 0
    assert str(small) in capsys.readouterr().err


def test_bad_landmark_argument(plys, tmp_path, capsys):
    assert main(["indices", "--out", str(tmp_path / "i.json"), "--vp", "1,2", str(plys / "a.ply")]) != 0
    assert "--vp" in capsys.readouterr().err


def test_torsoscan_has_every_command_and_the_engines_parser_only_its_own():
    from analysis.cli import build_parser
    from recon_engine import cli as engine_cli

    def commands(parser):
        return set(next(a for a in parser._actions if a.dest == "command").choices)

    engine = {"simulate", "calibrate", "stability", "reconstruct", "reconstruct-arm"}
    assert commands(engine_cli.build_parser()) == engine
    assert commands(build_parser()) == engine | {"compare", "indices"}

