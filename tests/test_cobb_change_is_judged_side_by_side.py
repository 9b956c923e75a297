"""The Cobb estimate of an S has a curve on each side: a change is judged side by side, so two curves that
bend about alike (a double major) do not read as a change when the larger one changes side between scans."""

import pytest


def _cobb(right, left):
    return {"cobb_estimate_deg": {"max": right if right >= left else -left,
                                  "right": {"size": right, "level": 0.64, "height_mm": 290.0},
                                  "left": {"size": left, "level": 0.28, "height_mm": 125.0}}}


def test_a_double_major_whose_larger_curve_changes_side_is_no_change():
    from analysis.repeatability import index_changes

    c = index_changes(_cobb(20.1, 19.6), _cobb(19.7, 20.0), {"cobb_estimate_deg.max": {"mdc": 3.0}})
    c = c["cobb_estimate_deg.max"]
    # the signed major read +20.1 then -20.0: 40 deg apart; side by side each curve moved by under half a degree
    assert abs(c["change"]) < 0.5 and c["exceeds_mdc"] is False
    assert {s["side"] for s in c["sides"]} == {"right", "left"}


def test_a_progressing_curve_is_flagged_on_its_side():
    from analysis.repeatability import index_changes

    c = index_changes(_cobb(20.0, 12.0), _cobb(27.5, 12.4), {"cobb_estimate_deg.max": {"mdc": 3.0}})
    c = c["cobb_estimate_deg.max"]
    assert c["change"] == pytest.approx(7.5) and c["exceeds_mdc"] is True
    right = next(s for s in c["sides"] if s["side"] == "right")
    assert right["exceeds_mdc"] is True and right["change"] == pytest.approx(7.5)
