"""A clinician corrects a landmark: the indices are computed again from it; bad input is refused."""

import pytest

from tests.patient_records import correct_sacral_point
from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_a_corrected_sacral_point_is_used(client, charlie, patient_with_two_visits):  # noqa: F811
    rec, auto, moved, r = correct_sacral_point(client, charlie, patient_with_two_visits.visits.first())
    assert r.status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": moved}
    assert rec.indices["landmarks"]["sacral_point"]["source"] != "auto"
    # the corrected point is kept, laid onto the skin (a few mm along the depth at most)
    assert rec.indices["landmarks"]["sacral_point"]["position_mm"] == pytest.approx(moved, abs=3.0)


@pytest.mark.django_db
def test_it_rejects_a_landmark_that_is_not_three_numbers(client, charlie, olga, patient_with_two_visits):  # noqa: F811
    visit = patient_with_two_visits.visits.first()
    client.force_login(charlie)
    r = client.post(f"/visits/{visit.pk}/landmarks", {"vertebra_prominens": "12, 40"})
    assert r.status_code == 400 and b"three numbers" in r.content
    client.force_login(olga)
    assert client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": "1 2 3"}).status_code == 404


@pytest.mark.django_db
def test_marked_dimples_make_the_pelvic_figures_measurable(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    visit = patient_with_two_visits.visits.first()
    rec = Reconstruction.objects.get(session__visit=visit)
    sp = rec.indices["landmarks"]["sacral_point"]["position_mm"]
    left, right = [sp[0] + 45.0, sp[1], sp[2] + 30.0], [sp[0] - 45.0, sp[1], sp[2] + 36.0]
    client.force_login(charlie)
    r = client.post(f"/visits/{visit.pk}/landmarks", {"dimple_left": " ".join(map(str, left)),
                                                      "dimple_right": " ".join(map(str, right))})
    assert r.status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks == {"dimple_left": left, "dimple_right": right}
    assert rec.indices["landmarks"]["dimple_left"]["source"] == "clinician"
    assert abs(rec.indices["pelvic_obliquity_mm"]) == pytest.approx(6.0, abs=0.5)
    assert "pelvic_obliquity_mm" not in (rec.indices.get("not_measurable") or {}).get("indices", [])
