import json

import numpy as np
import pytest

from recon_engine.camera import Camera
from recon_engine.formats import Calibration, FormatError, read_calibration, write_calibration


def _calibration():
    cam = Camera(40, 30, 100.0, 100.5, 20.1, 14.9, [-0.1, 0.01, 0.001, 0.0, 0.0], np.eye(3), [1.0, 2.0, 3.0])
    return Calibration("RIG-T", "2026-11-22T08:00:00+00:00", "testfield pose 0", {"A1": cam},
                       {"sigma0": 0.9, "camera_extra": {"A1": {"residual_rms_px": 0.1}}})


def test_it_round_trips_with_extra_keys(tmp_path):
    write_calibration(tmp_path / "c.json", _calibration())
    c = read_calibration(tmp_path / "c.json")
    assert c.cameras["A1"].fx == 100.0 and np.allclose(c.cameras["A1"].C, [1, 2, 3])
    assert c.extra["sigma0"] == 0.9 and c.extra["camera_extra"]["A1"]["residual_rms_px"] == 0.1


def _broken(tmp_path, change):
    write_calibration(tmp_path / "c.json", _calibration())
    obj = json.loads((tmp_path / "c.json").read_text())
    change(obj)
    (tmp_path / "c.json").write_text(json.dumps(obj))
    return tmp_path / "c.json"


def test_it_rejects_wrong_format(tmp_path):
    with pytest.raises(FormatError, match="format is 'torso-rig/1', expected 'torso-calibration/1'"):
        read_calibration(_broken(tmp_path, lambda o: o.update(format="torso-rig/1")))


def test_it_rejects_a_missing_key_naming_the_camera(tmp_path):
    with pytest.raises(FormatError, match="missing required key 'cy' for camera 'A1'"):
        read_calibration(_broken(tmp_path, lambda o: o["cameras"]["A1"].pop("cy")))


def test_it_rejects_a_short_distortion_vector(tmp_path):
    with pytest.raises(FormatError, match=r"camera 'A1' dist: shape \(4,\), expected \(5,\)"):
        read_calibration(_broken(tmp_path, lambda o: o["cameras"]["A1"].update(dist=[0, 0, 0, 0])))


def test_it_rejects_a_matrix_that_is_no_rotation(tmp_path):
    with pytest.raises(FormatError, match="camera 'A1' R: not a rotation matrix"):
        read_calibration(_broken(tmp_path, lambda o: o["cameras"]["A1"].update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]])))
