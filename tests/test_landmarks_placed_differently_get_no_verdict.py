"""A landmark marked on one scan and found automatically on the other: only the figures read at the apex are judged."""

from analysis.repeatability import index_changes, placed_differently


def _report(sp_source, length, imbalance, lateral):
    return {"landmarks": {"vertebra_prominens": {"source": "auto"}, "sacral_point": {"source": sp_source}},
            "trunk_length_mm": length, "trunk_imbalance_mm": imbalance, "trunk_inclination_mm": -45.0,
            "lateral_deviation_mm": {"rms": lateral}}


MDC = {"trunk_length_mm": {"mdc": 10.0}, "trunk_imbalance_mm": {"mdc": 5.0},
       "lateral_deviation_mm.rms": {"mdc": 2.0}}


def test_it_gives_no_verdict_on_the_offsets_of_a_landmark_placed_two_ways():
    marked, found = _report("clinician", 480.0, 1.0, 3.0), _report("auto", 500.0, 9.0, 3.5)
    assert placed_differently(marked, found) == ["sacral_point"]
    ch = index_changes(marked, found, MDC)
    for k in ("trunk_length_mm", "trunk_imbalance_mm", "trunk_inclination_mm"):
        assert ch[k]["exceeds_mdc"] is None
        assert "sacral point was marked on one scan" in ch[k]["no_verdict"]
    assert ch["trunk_length_mm"]["change"] == 20.0  # the change is still shown
    # the lateral deviation is measured from the line joining the trunk's ends: the two scans put them apart
    assert ch["lateral_deviation_mm.rms"]["exceeds_mdc"] is None
    assert "sacral point was marked on one scan" in ch["lateral_deviation_mm.rms"]["no_verdict"]


def test_it_still_judges_the_figures_read_at_the_apex():
    marked, found = _report("clinician", 480.0, 1.0, 3.0), _report("auto", 500.0, 9.0, 3.5)
    for r, rot, hump in ((marked, 8.0, 5.0), (found, 14.0, 5.5)):
        r["surface_rotation_deg"] = {"max": rot, "right": {"size": rot}, "left": None}
        r["hump_mm"], r["hump"] = hump, {"max": hump, "right": {"size": hump}, "left": None}
    mdc = {**MDC, "surface_rotation_deg.max": {"mdc": 1.3}, "hump_mm": {"mdc": 3.0}}
    ch = index_changes(marked, found, mdc)
    assert ch["surface_rotation_deg.max"]["exceeds_mdc"] is True and "no_verdict" not in ch["surface_rotation_deg.max"]
    assert ch["hump_mm"]["exceeds_mdc"] is False and "no_verdict" not in ch["hump_mm"]
    assert ch["lateral_deviation_mm.rms"]["exceeds_mdc"] is None


def test_it_judges_landmarks_placed_the_same_way():
    a, b = _report("clinician", 480.0, 1.0, 3.0), _report("clinician", 500.0, 9.0, 3.0)
    assert placed_differently(a, b) == []
    ch = index_changes(a, b, MDC)
    assert ch["trunk_length_mm"]["exceeds_mdc"] is True and "no_verdict" not in ch["trunk_length_mm"]
