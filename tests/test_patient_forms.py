"""Patients and visits are made and edited in the pages, validated, within the user's clinics."""

import pytest

from clinic.models import Patient, Visit


@pytest.mark.django_db
def test_it_creates_a_patient_and_keeps_the_user_on_the_form_with_the_error(client, charlie, clinic):
    Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin")
    client.force_login(charlie)
    r = client.post("/patients/new", {"clinic": clinic.pk, "identifier": "P-1", "name": "Sam"})
    assert r.status_code == 400
    assert "already has a patient with the identifier P-1" in r.content.decode()
    r = client.post("/patients/new", {"clinic": clinic.pk, "identifier": "P-2", "name": "Sam",
                                      "date_of_birth": "2099-01-01"})
    assert r.status_code == 400 and "cannot be in the future" in r.content.decode()
    r = client.post("/patients/new", {"clinic": clinic.pk, "identifier": "P-2", "name": "Sam",
                                      "date_of_birth": "2014-05-02"})
    sam = Patient.objects.get(identifier="P-2")
    assert r.status_code == 302 and r["Location"] == f"/patients/{sam.pk}/"


@pytest.mark.django_db
def test_it_creates_and_edits_a_visit_with_its_note(client, charlie, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin", date_of_birth="2014-01-01")
    client.force_login(charlie)
    r = client.post(f"/patients/{p.pk}/visits/new", {"date": "2010-01-01", "reason": "baseline"})
    assert r.status_code == 400 and "before the patient" in r.content.decode()
    r = client.post(f"/patients/{p.pk}/visits/new", {"date": "2026-07-01", "reason": "baseline", "notes": "Risser 2"})
    v = Visit.objects.get(patient=p)
    assert r.status_code == 302 and v.notes == "Risser 2" and v.clinician == charlie
    r = client.post(f"/visits/{v.pk}/edit", {"date": "2026-07-02", "reason": "baseline", "notes": "Risser 3"})
    v.refresh_from_db()
    assert r.status_code == 302 and v.notes == "Risser 3" and str(v.date) == "2026-07-02"


@pytest.mark.django_db
def test_a_user_of_another_clinic_cannot_reach_the_forms(client, olga, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin")
    client.force_login(olga)
    assert client.get(f"/patients/{p.pk}/edit").status_code == 404
    assert client.post(f"/patients/{p.pk}/visits/new", {"date": "2026-07-01"}).status_code == 404
    r = client.post("/patients/new", {"clinic": clinic.pk, "identifier": "P-9", "name": "Sam"})
    assert r.status_code == 400 and not Patient.objects.filter(identifier="P-9").exists()
