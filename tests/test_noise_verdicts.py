"""Noise verdicts: an MDC flags nothing until it rests on enough repeat pairs, and says how uncertain it is."""

import pytest

from analysis.repeatability import MIN_REPEAT_PAIRS, index_changes, mdc_from_index_pairs, usable_mdc


def _pairs(n, spread=1.0):
    # re-scans whose surface rotation differs by +-spread degrees
    return [({"surface_rotation_deg": {"max": 10.0}}, {"surface_rotation_deg": {"max": 10.0 + (spread if k % 2 else -spread)}})
            for k in range(n)]


def test_it_flags_nothing_from_one_repeat_pair():
    mdc = mdc_from_index_pairs(_pairs(1))
    assert mdc["surface_rotation_deg.max"]["n"] == 1
    ch = index_changes({"surface_rotation_deg": {"max": 10.0}}, {"surface_rotation_deg": {"max": 30.0}}, usable_mdc(mdc))
    assert ch["surface_rotation_deg.max"]["exceeds_mdc"] is None  # no verdict, neither red nor green


def test_it_flags_with_enough_repeat_pairs_and_gives_the_interval():
    mdc = mdc_from_index_pairs(_pairs(MIN_REPEAT_PAIRS))
    m = mdc["surface_rotation_deg.max"]
    assert m["mdc_estimate"] == pytest.approx(1.96 * 1.0, rel=1e-6)  # SEM = spread / sqrt(2), MDC = 1.96 sqrt(2) SEM
    lo, hi = m["ci95"]
    assert lo < m["mdc_estimate"] < hi and hi < 2 * m["mdc_estimate"]
    # a change is judged against the interval's upper bound: beyond noise even if the scanner were that noisy
    assert m["mdc"] == pytest.approx(hi)
    usable = usable_mdc(mdc)
    ch = index_changes({"surface_rotation_deg": {"max": 10.0}}, {"surface_rotation_deg": {"max": 15.0}}, usable)
    assert ch["surface_rotation_deg.max"]["exceeds_mdc"] is True
    ch = index_changes({"surface_rotation_deg": {"max": 10.0}}, {"surface_rotation_deg": {"max": 10.5}}, usable)
    assert ch["surface_rotation_deg.max"]["exceeds_mdc"] is False


def test_the_scanners_repeatability_is_read_labelled_and_needs_enough_pairs(tmp_path):
    import json

    from analysis.repeatability import scanner_mdc

    mdc = mdc_from_index_pairs(_pairs(MIN_REPEAT_PAIRS))
    mdc["hump_mm"] = {"mdc": 1.0, "sem": 0.4, "n": 3}  # too few pairs: never used
    path = tmp_path / "scanner_mdc.json"
    path.write_text(json.dumps({"source": "test", "pairs": MIN_REPEAT_PAIRS, "mdc": mdc}))
    got = scanner_mdc(path)
    assert set(got) == {"surface_rotation_deg.max"} and got["surface_rotation_deg.max"]["source"] == "scanner"
    assert scanner_mdc(tmp_path / "missing.json") == {}
    # a file written with the point estimate as "mdc" is read with the judged (upper-bound) MDC
    old = {"surface_rotation_deg.max": {"mdc": 1.96, "sem": 1.0, "n": MIN_REPEAT_PAIRS}}
    path.write_text(json.dumps({"source": "test", "pairs": MIN_REPEAT_PAIRS, "mdc": old}))
    got = scanner_mdc(path)["surface_rotation_deg.max"]
    assert got["mdc_estimate"] == pytest.approx(1.96) and got["mdc"] == pytest.approx(got["ci95"][1])


def test_the_scanners_repeatability_comes_from_reconstructed_rescans_on_a_rig_like_the_clinics(tmp_path):
    import json

    from analysis.repeatability import scanner_mdc

    def entry(mdc):
        return {"mdc": mdc, "sem": mdc / 2.77, "n": MIN_REPEAT_PAIRS}

    path = tmp_path / "scanner_mdc.json"
    path.write_text(json.dumps({
        "mdc": {"hump_mm": entry(1.0), "asymmetry_mm": entry(0.1)},
        "rigs": {"demo": {"image_size_px": [720, 480], "mdc": {"hump_mm": entry(4.0), "asymmetry_mm": entry(0.05)}},
                 "paper": {"image_size_px": [3000, 2000], "mdc": {"hump_mm": entry(2.0)}}}}))
    coarse = scanner_mdc(path, image_width=720)
    # the reconstruction adds its noise: the larger of the two sets, and which one it was is said
    assert coarse["hump_mm"]["mdc_estimate"] == pytest.approx(4.0)
    assert coarse["hump_mm"]["measured_on"] == "reconstructed re-scans, 720 x 480 px rig"
    assert coarse["asymmetry_mm"]["measured_on"] == "true surfaces"
    assert scanner_mdc(path, image_width=3000)["hump_mm"]["mdc_estimate"] == pytest.approx(2.0)
    # a rig sharper than the demo's but coarser than the paper's: the demo's set (a sharper rig is no noisier)
    assert scanner_mdc(path, image_width=1000)["hump_mm"]["mdc_estimate"] == pytest.approx(4.0)
    # coarser than every simulated rig, or unknown: the coarsest set
    assert scanner_mdc(path, image_width=480)["hump_mm"]["mdc_estimate"] == pytest.approx(4.0)
    assert scanner_mdc(path)["hump_mm"]["mdc_estimate"] == pytest.approx(4.0)
