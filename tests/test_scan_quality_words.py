"""A visit says in words whether its scan is good, usable or to be repeated; the figures fold away."""

import pytest

from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


def _pair(a, b, distance, overlap):
    return {"a": a, "b": b, "average_normal_distance_mm": distance, "matched_fraction": 0.3,
            "overlap_matched_fraction": overlap, "pairs": 500}


@pytest.mark.django_db
def test_it_gives_the_quality_verdict_in_words_and_folds_the_figures(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    visit = patient_with_two_visits.visits.first()
    rec = Reconstruction.objects.get(session__visit=visit)
    rec.report = {"registration": {"pairs": [_pair("A", "B", 0.2, 0.99), _pair("B", "C", 0.25, 0.98)]}}
    rec.save()
    client.force_login(charlie)
    html = client.get(f"/visits/{visit.pk}/").content.decode()
    assert "Scan quality: Good scan" in html or "Scan quality: Usable scan" in html  # landmarks may lower it
    details = html[html.index("<details"):html.index("</details>")]
    assert "<summary>Technical details" in details
    assert "Average normal distance (mm)" in details and "Captures and jobs" in details
    before = html[:html.index("<details")]
    assert "Average normal distance" not in before and "Point–patch pairs" not in before

    # arms that fit badly together: repeat the scan, and why
    rec.report = {"registration": {"pairs": [_pair("A", "B", 1.6, 0.99), _pair("B", "C", 0.2, 0.4)]}}
    rec.status = "partial"
    rec.save()
    html = client.get(f"/visits/{visit.pk}/").content.decode()
    assert "Scan quality: Repeat the scan" in html
    reasons = html[html.index('id="quality"'):html.index("</section>")]
    assert "Arms A and B fit together only to 1.60 mm" in reasons
    assert "Only 40 % of the overlap of arms B and C matched" in reasons
    assert "Part of the torso is missing" in reasons
