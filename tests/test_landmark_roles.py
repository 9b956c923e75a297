"""Correcting a landmark is a clinical judgement: clinicians and administrators, not technicians."""

import pytest

from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_it_refuses_a_technician_and_lets_a_clinician(client, alice, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    visit = patient_with_two_visits.visits.first()
    rec = Reconstruction.objects.get(session__visit=visit)
    client.force_login(alice)
    assert b"Recompute indices" not in client.get(f"/visits/{visit.pk}/").content
    r = client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": "1 2 3"})
    assert r.status_code == 403 and b"technician cannot do this" in r.content
    rec.refresh_from_db()
    assert rec.landmarks is None

    client.force_login(charlie)
    assert b"Recompute indices" in client.get(f"/visits/{visit.pk}/").content
    auto = rec.indices["landmarks"]["sacral_point"]["position_mm"]
    assert client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": " ".join(map(str, auto))}).status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": auto}
