"""A landmark marked on one scan and found automatically on the other: its own offsets are not judged."""

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
    # figures that are not the landmarks' own offsets are judged as before
    assert ch["lateral_deviation_mm.rms"]["exceeds_mdc"] is False


def test_it_judges_landmarks_placed_the_same_way():
    a, b = _report("clinician", 480.0, 1.0, 3.0), _report("clinician", 500.0, 9.0, 3.0)
    assert placed_differently(a, b) == []
    ch = index_changes(a, b, MDC)
    assert ch["trunk_length_mm"]["exceeds_mdc"] is True and "no_verdict" not in ch["trunk_length_mm"]
