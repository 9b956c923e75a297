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
    assert not result["cameras"]["C2"]["stable"]


def test_the_threshold_follows_the_calibrations_precision(calibration_1, calibration_2):
    a, b = calibration_1[0], calibration_2[0]
    m = compare_calibrations(a, b)["cameras"]["A1"]
    spread = m["null_spread_px"]
    # a rotation absorbs the principal point's uncertainty: ROT is the sharper measure
    assert spread["rot_px"] < spread["zrot_px"]
    assert m["threshold_px"]["zrot_px"] >= 2.5 * spread["zrot_px"] - 1e-9
