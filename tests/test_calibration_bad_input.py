"""Calibration refuses the wrong captures and survives a camera that saw too little."""

import json
import shutil

import numpy as np
import pytest

from recon_engine.calibration import calibrate
from recon_engine.formats import FormatError, read_capture, read_rig, read_testfield, write_json


def _inputs(scenario):
    rig = read_rig(scenario / "rig.json")
    tf = read_testfield(scenario / "testfield.json")
    caps = [read_capture(p, rig) for p in sorted((scenario / "captures").glob("testfield-pose*"))]
    return rig, tf, caps


def test_it_rejects_a_capture_of_the_wrong_kind(rig_session_1, tmp_path):
    rig, tf, caps = _inputs(rig_session_1)
    bad = tmp_path / "cap"
    shutil.copytree(caps[1].source, bad)
    m = json.loads((bad / "capture.json").read_text())
    m["kind"] = "torso"
    write_json(bad / "capture.json", m)
    with pytest.raises(FormatError, match=r"cap: kind is 'torso': calibration needs 'testfield' captures"):
        calibrate([caps[0], read_capture(bad, rig)], rig, tf)


def test_it_rejects_a_test_field_name_that_does_not_match(rig_session_1):
    rig, tf, caps = _inputs(rig_session_1)
    other = type(tf)("another-tower", tf.aruco_dictionary, tf.markers, tf.sigma_mm)
    with pytest.raises(FormatError, match="testfield is 'tower-sim', but the test field given is 'another-tower'"):
        calibrate(caps, rig, other)


def test_a_camera_with_too_few_targets_is_named_and_the_others_calibrated(rig_session_1, tmp_path):
    rig, tf, caps = _inputs(rig_session_1)
    import cv2

    from recon_engine.formats import load_images, write_capture

    blinded = []
    for cap in caps:
        images = load_images(cap, rig)
        images["B3"] = np.full_like(images["B3"], 12)  # lens cap on
        blinded.append(write_capture(tmp_path / f"pose{cap.pose}", kind="testfield", rig=rig.serial,
                                     captured_at=cap.captured_at, images=images, testfield=tf.name, pose=cap.pose))
    calib, report = calibrate(blinded, rig, tf)
    assert "B3" not in calib.cameras and len(calib.cameras) == 19
    assert "B3" in report.failed_cameras and "usable markers" in report.failed_cameras["B3"]
    assert calib.extra["failed_cameras"]["B3"] == report.failed_cameras["B3"]
    assert cv2 is not None
