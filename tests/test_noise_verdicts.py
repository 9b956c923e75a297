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
    assert m["mdc"] == pytest.approx(1.96 * 1.0, rel=1e-6)  # SEM = spread / sqrt(2), MDC = 1.96 sqrt(2) SEM
    lo, hi = m["ci95"]
    assert lo < m["mdc"] < hi and hi < 2 * m["mdc"]
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
