"""Self-calibrating bundle adjustment on the simulated test field (tiny preset)."""

import numpy as np

from recon_engine.calibration import compare_cameras, working_volume_points
from recon_engine.formats import read_calibration, read_rig


def test_it_calibrates_every_camera_close_to_the_truth(rig_session_1, calibration_1):
    calib, report = calibration_1
    rig = read_rig(rig_session_1 / "rig.json")
    assert sorted(calib.cameras) == sorted(rig.camera_ids) and not report.failed_cameras
    truth = read_calibration(rig_session_1 / "truth" / "calibration.json")
    pts = working_volume_points()
    figures = [compare_cameras(calib.cameras[c], truth.cameras[c], pts) for c in calib.cameras]
    # tiny images (2.1 mm pixels): loose bounds; the paper-scale figures are in docs/benchmarks.md
    assert np.median([f["image_rms_px"] for f in figures]) < 0.08
    assert np.median([f["principal_distance_rel"] for f in figures]) < 0.003
    assert np.median([f["centre_mm"] for f in figures]) < 6.0
    assert np.median([f["rotation_deg"] for f in figures]) < 0.15


def test_residuals_match_the_measurement_precision(calibration_1):
    calib, report = calibration_1
    rms = np.array([v for v in report.residual_rms_px.values()])
    assert np.all(rms < 0.3) and 0.3 < report.sigma0 < 3.0
    assert set(report.residual_rms_by_pose_px) == {"0", "1", "2"}
    assert report.inlier_fraction > 0.98


def test_the_result_carries_sigmas_and_arm_relative_orientations(calibration_1):
    calib, _ = calibration_1
    sig = calib.extra["sigmas"]["A1"]
    assert 0 < sig["fx"] < 20 and 0 < sig["cx"] < 20 and 0 < sig["X"] < 20
    arm = calib.extra["arms"]["B"]
    assert arm["reference_camera"] == "B1"
    assert np.allclose(arm["cameras"]["B1"]["R"], np.eye(3)) and np.allclose(arm["cameras"]["B1"]["C"], 0)
    assert abs(np.linalg.norm(arm["cameras"]["B2"]["C"]) - 800) < 50  # neighbours 0.8 m apart


def test_rejected_targets_are_counted_by_reason(calibration_1):
    _, report = calibration_1
    assert report.dropped.get("edge_on", 0) > 0  # the tower's side faces
    assert all(isinstance(v, int) and v >= 0 for v in report.dropped.values())
