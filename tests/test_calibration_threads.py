"""The test field's images are measured in threads; the targets and the report do not depend on them."""

import numpy as np

from recon_engine.calibration import CalibrationConfig, CalibrationReport, measure_targets, remeasure_targets
from recon_engine.formats import read_calibration, read_capture, read_rig, read_testfield


def _measure(scenario, monkeypatch, threads: str):
    monkeypatch.setenv("TORSOSCAN_THREADS", threads)
    rig = read_rig(scenario / "rig.json")
    tf = read_testfield(scenario / "testfield.json")
    caps = [read_capture(scenario / "captures" / "testfield-pose0", rig)]  # 20 images: enough for the order
    report, cache = CalibrationReport(), {}
    targets = measure_targets(caps, rig, tf, report, CalibrationConfig(), images=cache)
    # the second pass: edges undistorted with the cameras' IOPs (here the true ones)
    cameras = read_calibration(scenario / "truth" / "calibration.json").cameras
    again = remeasure_targets(targets, cache, cameras, report, CalibrationConfig())
    return targets, again, report, cache


def test_it_measures_the_same_targets_with_one_thread_or_two(rig_session_1, monkeypatch):
    one, again_one, report_one, cache_one = _measure(rig_session_1, monkeypatch, "1")
    two, again_two, report_two, cache_two = _measure(rig_session_1, monkeypatch, "2")
    assert [(t.camera, t.pose) for t in one] == [(t.camera, t.pose) for t in two]
    assert sum(len(t.ids) for t in one) > 100 and sum(len(t.ids) for t in again_one) > 100
    for a, b in zip(one + again_one, two + again_two):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.corners, b.corners)
    assert report_one.dropped == report_two.dropped
    assert report_one.dropped_by_camera == report_two.dropped_by_camera
    assert set(cache_one) == set(cache_two) == {(t.camera, t.pose) for t in one}
