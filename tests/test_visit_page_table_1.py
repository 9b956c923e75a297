"""The visit page's Table 1 shows how much of each overlap matched, and copes with reports that predate it."""

import pytest

from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


def _pair(a, b, **extra):
    return {"a": a, "b": b, "average_normal_distance_mm": 0.0375, "matched_fraction": 0.081, "pairs": 3256, **extra}


@pytest.mark.django_db
def test_it_shows_the_share_of_each_overlap_matched(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    visit = patient_with_two_visits.visits.first()
    rec = Reconstruction.objects.get(session__visit=visit)
    # an older report without the field, beside a current one
    rec.report = {**rec.report, "registration": {"pairs": [_pair("D", "A", overlap_matched_fraction=0.9997),
                                                            _pair("A", "B")]}}
    rec.save()
    client.force_login(charlie)
    r = client.get(f"/visits/{visit.pk}/")
    assert r.status_code == 200
    html = r.content.decode()
    assert "Overlap matched" in html
    assert "100.0 %" in html and "8.1 %" in html  # 0.9997 rounds to 100.0 %; the points' share is 8.1 %
    older = html[html.index("<td>A–B</td>"):]
    assert older[:older.index("</tr>")].count('<td class="n">–</td>') == 1  # the older report's row


@pytest.mark.django_db
def test_a_user_of_another_clinic_gets_404(client, olga, patient_with_two_visits):  # noqa: F811
    client.force_login(olga)
    assert client.get(f"/visits/{patient_with_two_visits.visits.first().pk}/").status_code == 404
