"""The patient's history opens with a headline: what changed, by how much, where, and whether beyond noise."""

import pytest

from analysis.repeatability import INDEX_FIGURES, MIN_REPEAT_PAIRS
from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


def _headline(html):
    start = html.index('id="headline"')
    return html[start:html.index("<h2>Visits</h2>")]


@pytest.mark.django_db
def test_it_states_the_changes_and_says_no_verdict_is_possible_yet(client, charlie, patient_with_two_visits,  # noqa: F811
                                                                    monkeypatch):
    import analysis.repeatability

    # no repeatability of the scanner's either (an installation without analysis/scanner_mdc.json)
    monkeypatch.setattr(analysis.repeatability, "scanner_mdc", lambda path=None, image_width=None: {})
    client.force_login(charlie)
    html = client.get(f"/patients/{patient_with_two_visits.pk}/").content.decode()
    head = _headline(html)
    assert "Since the baseline" in head and "4 months" in head
    assert "No noise verdict is possible yet" in head
    assert f"needs {MIN_REPEAT_PAIRS} same-day re-scans" in head and "given 0 so far" in head
    # the changes are still stated, with their size and where they are now largest
    assert "Changes (sizes only, no noise verdict)" in head
    assert "Trunk rotation, largest" in head and "Largest now:" in head and "above the sacral point" in head
    assert "beyond the scanner's noise" not in head
    # growth apart, never as a change of the deformity
    growth = head[head.index("Growth (reported apart"):]
    assert "Trunk length C7 – sacral point" in growth


@pytest.mark.django_db
def test_it_says_which_changed_beyond_noise_with_enough_repeat_pairs(client, charlie, patient_with_two_visits,  # noqa: F811
                                                                      monkeypatch):
    from clinic import analysis_step

    # enough repeat pairs: a tiny noise for every index but the asymmetry, whose noise is huge
    mdc = {k: {"mdc": 0.01, "n": MIN_REPEAT_PAIRS} for k in INDEX_FIGURES}
    mdc["asymmetry_mm"] = {"mdc": 1000.0, "n": MIN_REPEAT_PAIRS}
    monkeypatch.setattr(analysis_step, "clinic_mdc", lambda clinic, usable_only=True: mdc)
    monkeypatch.setattr(analysis_step, "repeat_pairs", lambda clinic: MIN_REPEAT_PAIRS)
    client.force_login(charlie)
    head = _headline(client.get(f"/patients/{patient_with_two_visits.pk}/").content.decode())
    assert "No noise verdict is possible yet" not in head
    beyond = head[head.index("Changed beyond the scanner's noise"):head.index("Within the scanner's noise")]
    assert "Trunk rotation, largest" in beyond and "▲" in beyond
    within = head[head.index("Within the scanner's noise"):]
    assert "Back asymmetry (mirror)" in within.split("</p>")[0]
    # growth is never a change beyond noise, however small the noise
    assert "Trunk length" not in beyond


@pytest.mark.django_db
def test_until_the_clinic_has_its_own_re_scans_the_verdicts_rest_on_the_scanners_repeatability(
        client, charlie, patient_with_two_visits):  # noqa: F811
    from analysis.repeatability import scanner_mdc

    assert scanner_mdc(), "analysis/scanner_mdc.json (benchmarks/bench_bodies.py --write-mdc) is shipped"
    client.force_login(charlie)
    head = _headline(client.get(f"/patients/{patient_with_two_visits.pk}/").content.decode())
    assert "the scanner's own repeatability" in head and "No noise verdict is possible yet" not in head
