"""A staff client's retried request (its first answer lost) makes one visit, not two, when it repeats its
Idempotency-Key; a new patient raced by another request is a 409, not a server error."""

import json

import pytest

from clinic import api
from clinic.models import Patient, Visit


def _post(client, path, body, **extra):
    return client.post(path, data=json.dumps(body), content_type="application/json", **extra)


@pytest.mark.django_db
def test_a_retried_visit_with_its_idempotency_key_is_the_same_visit(client, charlie, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin")
    client.force_login(charlie)
    body = {"date": "2027-01-05", "reason": "brace check"}
    first = _post(client, f"/api/patients/{p.pk}/visits", body, HTTP_IDEMPOTENCY_KEY="visit-2027-01-05-a")
    again = _post(client, f"/api/patients/{p.pk}/visits", body, HTTP_IDEMPOTENCY_KEY="visit-2027-01-05-a")
    assert (first.status_code, again.status_code) == (201, 200) and first.json() == again.json()
    assert Visit.objects.filter(patient=p).count() == 1
    # another key (or none) is another visit
    assert _post(client, f"/api/patients/{p.pk}/visits", body, HTTP_IDEMPOTENCY_KEY="b").status_code == 201
    assert _post(client, f"/api/patients/{p.pk}/visits", body).status_code == 201
    assert Visit.objects.filter(patient=p).count() == 3


@pytest.mark.django_db(transaction=True)
def test_a_patient_made_by_another_request_meanwhile_is_a_conflict(client, charlie, clinic, monkeypatch):
    Patient.objects.create(clinic=clinic, identifier="P-7", name="the other request's")  # committed just after ...
    real_filter = Patient.objects.filter
    calls = []

    def checked_before_the_other_commit(*args, **kw):  # ... this request's check, which saw no P-7
        calls.append(kw)
        return Patient.objects.none() if len(calls) == 1 else real_filter(*args, **kw)

    monkeypatch.setattr(api.Patient.objects, "filter", checked_before_the_other_commit)
    client.force_login(charlie)
    client.raise_request_exception = False
    r = _post(client, "/api/patients", {"clinic": clinic.pk, "identifier": "P-7", "name": "Sam"})
    assert calls and calls[0].get("identifier") == "P-7"
    assert r.status_code == 409 and "P-7" in r.json()["detail"], r.status_code
    monkeypatch.undo()
    assert Patient.objects.filter(identifier="P-7").count() == 1
