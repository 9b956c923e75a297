"""ZROT, ROT and SPR between calibrations (Habib and Morgan)."""

from dataclasses import replace

import numpy as np
import pytest

from recon_engine.camera import Camera
from recon_engine.formats import Calibration
from recon_engine.stability import bundle_measures, compare_calibrations, history

CAM = Camera(3000, 2000, 7450.0, 7450.0, 1510.0, 990.0, [-0.1, 0.2, 3e-4, -2e-4, 0.0])


def test_identical_bundles_coincide():
    m = bundle_measures(CAM, CAM)
    assert max(m.values()) < 1e-9


def test_a_principal_distance_change_shows_in_zrot_and_rot_but_resection_absorbs_it():
    m = bundle_measures(CAM, replace(CAM, fx=CAM.fx * 1.001, fy=CAM.fy * 1.001))
    assert m["zrot_px"] > 0.8 and m["rot_px"] > 0.8 and m["spr_px"] < 0.05


def test_a_principal_point_shift_shows_in_zrot_only():
    m = bundle_measures(CAM, replace(CAM, cx=CAM.cx + 2.0))
    assert m["zrot_px"] == pytest.approx(2.0, abs=1e-6) and m["rot_px"] < 0.1 and m["spr_px"] < 0.05


def test_it_refuses_an_unknown_criterion():
    c = Calibration("R", "t", "f", {"A1": CAM})
    with pytest.raises(ValueError, match="unknown stability criterion 'xyz'"):
        compare_calibrations(c, c, criterion="xyz")


def test_history_against_first_and_previous():
    cals = [Calibration("R", f"2026-0{i + 1}-01", "f", {"A1": replace(CAM, cx=CAM.cx + 0.5 * i)}) for i in range(4)]
    h = history(cals, reference="first", threshold_px=1.2)
    assert [round(r["zrot_px"], 6) for r in h["cameras"]["A1"]] == [0.5, 1.0, 1.5]
    assert [r["stable"] for r in h["cameras"]["A1"]] == [True, True, False]
    assert h["trend_px_per_calibration"]["A1"]["zrot"] == pytest.approx(0.5)
    p = history(cals, reference="previous", threshold_px=1.0)
    assert all(r["stable"] for r in p["cameras"]["A1"])


def test_two_calibrations_of_the_unchanged_rig_are_stable(calibration_1, calibration_2):
    result = compare_calibrations(calibration_1[0], calibration_2[0])
    assert len(result["cameras"]) == 20
    stable = [m["stable"] for m in result["cameras"].values()]
    # 2.5 sigma on three measures: an occasional false alarm is expected, not a rule
    assert np.mean(stable) >= 0.9


def test_disturbed_lenses_are_found_unstable(calibration_1, calibration_disturbed):
    result = compare_calibrations(calibration_1[0], calibration_disturbed[0])
    assert not result["cameras"]["A3"]["stable"]
    c2 = result["cameras"]["C2"]
    assert not c2["stable"] and "arm" in c2["exceeds"]
    # the shift turns C2's rays in its arm by about 3 px whatever the adjustment made of it
    assert 2.0 < c2["arm_px"] < 4.0


def test_a_disturbed_camera_does_not_drag_its_arm_neighbours(calibration_1, calibration_disturbed):
    result = compare_calibrations(calibration_1[0], calibration_disturbed[0])
    for cam_id in ("C1", "C3", "C4", "C5"):
        m = result["cameras"][cam_id]
        assert "C2" not in m["arm_reference_cameras"]
        assert m["arm_px"] < m["threshold_px"]["arm_px"]


def test_the_arm_measure_ignores_the_arm_moving_as_a_whole(calibration_1):
    """An arm swung open carries its cameras rigidly: no camera of it is unstable."""
    from recon_engine.bundle import rodrigues

    calib = calibration_1[0]
    R = rodrigues(np.array([0.0, 0.0, np.radians(20.0)]))
    t = np.array([150.0, -80.0, 5.0])
    moved = dict(calib.cameras)
    for cam_id in calib.extra["arms"]["B"]["cameras"]:
        c = calib.cameras[cam_id]
        # world a -> world b: X_b = R X_a + t, so the camera's R becomes R_c R^T, its centre R C + t
        moved[cam_id] = replace(c, R=c.R @ R.T, C=R @ c.C + t)
    m = compare_calibrations(calib, replace(calib, cameras=moved), criterion="arm")["cameras"]
    assert all(m[c]["arm_px"] < 1e-3 for c in calib.extra["arms"]["B"]["cameras"])
    assert all(m[c]["stable"] for c in m)


def test_an_arm_camera_knocked_in_its_mount_is_unstable(calibration_1):
    """Same lens, but the camera turned by 2 px in its mount: its relative EOP no longer holds."""
    from recon_engine.bundle import rodrigues

    calib = calibration_1[0]
    c = calib.cameras["D3"]
    moved = dict(calib.cameras, D3=replace(c, R=rodrigues(np.array([0.0, 2.0 / c.fx, 0.0])) @ c.R))
    m = compare_calibrations(calib, replace(calib, cameras=moved))["cameras"]
    assert m["D3"]["arm_px"] == pytest.approx(2.0, rel=0.05)
    assert not m["D3"]["stable"] and m["D3"]["exceeds"] == ["arm"]
    assert all(m[o]["stable"] for o in ("D1", "D2", "D4", "D5"))


def test_the_threshold_follows_the_calibrations_precision(calibration_1, calibration_2):
    a, b = calibration_1[0], calibration_2[0]
    m = compare_calibrations(a, b)["cameras"]["A1"]
    spread = m["null_spread_px"]
    # a rotation absorbs the principal point's uncertainty: ROT is the sharper measure
    assert spread["rot_px"] < spread["zrot_px"]
    assert m["threshold_px"]["zrot_px"] >= 2.5 * spread["zrot_px"] - 1e-9
