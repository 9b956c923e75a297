"""Every page that shows a patient's data names the patient: name, identifier, date of birth and age."""

import datetime

import pytest

from tests.test_browser_comparison import compared, patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_it_names_the_patient_on_the_history_visit_comparison_and_picture_pages(client, charlie,
                                                                                  patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    p = patient_with_two_visits
    p.date_of_birth = datetime.date(2013, 3, 14)
    p.save()
    first, second = p.visits.all()
    compared(p)
    rec = Reconstruction.objects.get(session__visit=second)
    client.force_login(charlie)
    pages = [f"/patients/{p.pk}/", f"/visits/{first.pk}/", f"/visits/{second.pk}/",
             f"/patients/{p.pk}/compare/?earlier={first.pk}&later={second.pk}",
             f"/pictures/reconstruction/{rec.pk}/torso-back/", f"/patients/{p.pk}/edit",
             f"/patients/{p.pk}/visits/new", f"/visits/{first.pk}/edit"]
    for url in pages:
        r = client.get(url)
        assert r.status_code == 200, url
        html = r.content.decode()
        assert "Robin Browser" in html and "P-77" in html and "born 14 Mar 2013" in html, url
    # the visit page gives the age on the visit's day
    assert "age 13 y 3 mo on 1 Jul 2026" in client.get(f"/visits/{first.pk}/").content.decode()
