"""The RMS of a section index is over the levels SP-VP: an unread section between read ones counts with the
value interpolated from its neighbours, so two scans that could not read the same levels agree."""

import numpy as np

from analysis.indices import fill_between, rms


def test_it_fills_only_between_read_values():
    z = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 60.0])
    v = np.array([np.nan, 1.0, np.nan, np.nan, 4.0, np.nan])
    out = fill_between(z, v)
    assert np.isnan(out[0]) and np.isnan(out[-1])  # nothing to interpolate from beyond the read ends
    assert np.allclose(out[1:5], [1.0, 2.0, 3.0, 4.0])


def test_it_interpolates_in_height_not_in_index():
    out = fill_between([0.0, 10.0, 40.0], [0.0, np.nan, 4.0])
    assert np.isclose(out[1], 1.0)


def test_it_does_not_change_its_input():
    v = np.array([1.0, np.nan, 3.0])
    fill_between([0.0, 1.0, 2.0], v)
    assert np.isnan(v[1])


def test_one_read_value_is_left_as_it_is():
    out = fill_between([0.0, 1.0, 2.0], [np.nan, 5.0, np.nan])
    assert np.isnan(out[0]) and out[1] == 5.0 and np.isnan(out[2])


def test_two_scans_missing_different_levels_near_the_apex_agree():
    # one back's rotation profile (deg) at 37 levels, read on two scans that each lost three sections beside
    # the apex, at different levels (an arm against the flank)
    z = np.linspace(0.0, 450.0, 37)
    truth = 10.0 * np.exp(-0.5 * ((z - 300.0) / 60.0) ** 2)
    a, b = truth.copy(), truth.copy()
    a[25:28] = np.nan
    b[23:26] = np.nan
    dropped = abs(rms(a) - rms(b))
    filled = abs(rms(fill_between(z, a)) - rms(fill_between(z, b)))
    assert dropped > 0.1
    assert filled < dropped / 3
    assert abs(rms(fill_between(z, a)) - rms(truth)) < abs(rms(a) - rms(truth))
