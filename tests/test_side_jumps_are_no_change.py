"""A signed maximum that jumps sides between two scans of the same back (an S curve whose two sides are nearly
equal) is no change: such figures are compared side by side, for the flags and for the MDC alike."""

from analysis.repeatability import index_changes, mdc_from_index_pairs


def report(right, left):
    """The part of a torso-indices/1 report the comparison reads: each side's largest value and the signed max."""
    sides = {"right": None if right is None else {"size": right, "level": 0.6, "height_mm": 280.0},
             "left": None if left is None else {"size": left, "level": 0.35, "height_mm": 160.0}}
    signed = max([(right or 0.0), -(left or 0.0)], key=abs)
    return {"surface_rotation_deg": {"max": signed, "rms": 4.0, **sides}}


MDC = {"surface_rotation_deg.max": {"mdc": 1.0}}


def test_it_does_not_flag_a_maximum_that_jumped_sides():
    change = index_changes(report(8.0, 7.9), report(7.9, 8.1), MDC)["surface_rotation_deg.max"]
    assert abs(change["change"]) <= 0.25 and change["exceeds_mdc"] is False
    # the signed maxima themselves were +8.0 and -8.1: a "change" of 16 deg if taken as they stand
    assert (report(8.0, 7.9)["surface_rotation_deg"]["max"], report(7.9, 8.1)["surface_rotation_deg"]["max"]) \
        == (8.0, -8.1)


def test_it_flags_a_progression_on_the_side_that_progressed_and_says_which():
    change = index_changes(report(8.0, 3.0), report(13.0, 3.1), MDC)["surface_rotation_deg.max"]
    assert (change["earlier"], change["later"], change["exceeds_mdc"]) == (8.0, 13.0, True)
    change = index_changes(report(8.0, 3.0), report(8.1, 9.0), MDC)["surface_rotation_deg.max"]
    assert (change["earlier"], change["later"], change["exceeds_mdc"]) == (-3.0, -9.0, True)  # left: negative


def test_a_side_that_appears_counts_from_zero():
    change = index_changes(report(8.0, None), report(8.0, 4.0), MDC)["surface_rotation_deg.max"]
    assert (change["earlier"], change["later"]) == (-0.0, -4.0) and change["exceeds_mdc"] is True


def test_the_mdc_of_a_signed_maximum_ignores_side_jumps():
    pairs = [(report(8.0, 7.9), report(7.9, 8.1)), (report(5.0, 1.0), report(5.2, 1.0))] * 3
    mdc = mdc_from_index_pairs(pairs)["surface_rotation_deg.max"]
    assert mdc["n"] == 6 and mdc["mdc_estimate"] < 0.6 and mdc["mdc"] < 1.2  # side jumps would give ~30 deg


def hump_report(right, left):
    """The hump as the spec keeps it (one signed number) and its sides, as ``analyse_torso`` reports them."""
    sides = {"right": None if right is None else {"size": right, "level": 0.62, "height_mm": 290.0},
             "left": None if left is None else {"size": left, "level": 0.3, "height_mm": 140.0}}
    signed = max([(right or 0.0), -(left or 0.0)], key=abs)
    return {"hump_mm": signed, "hump": {"max": signed, **sides}}


def test_it_does_not_flag_a_hump_that_jumped_sides():
    # an S curve's thoracic hump on the right and lumbar hump on the left, nearly equal (seen on a rendered
    # re-scan: -17.1 mm, then +17.7 mm)
    change = index_changes(hump_report(17.0, 17.1), hump_report(17.7, 17.2), {"hump_mm": {"mdc": 3.0}})["hump_mm"]
    assert abs(change["change"]) <= 0.75 and change["exceeds_mdc"] is False
    change = index_changes(hump_report(17.0, 9.0), hump_report(23.0, 9.0), {"hump_mm": {"mdc": 3.0}})["hump_mm"]
    assert (change["earlier"], change["later"], change["exceeds_mdc"]) == (17.0, 23.0, True)
