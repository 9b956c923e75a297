"""A staff client's retried request (its first answer lost) makes one visit, not two, when it repeats its
Idempotency-Key; a new patient raced by another request is a 409, not a server error."""

import json
import uuid

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
    key = uuid.uuid4().hex  # the cache outlives a test's database: a key of its own
    first = _post(client, f"/api/patients/{p.pk}/visits", body, HTTP_IDEMPOTENCY_KEY=key)
    again = _post(client, f"/api/patients/{p.pk}/visits", body, HTTP_IDEMPOTENCY_KEY=key)
    assert (first.status_code, again.status_code) == (201, 200) and first.json() == again.json()
    assert Visit.objects.filter(patient=p).count() == 1
    # another key (or none) is another visit
    assert _post(client, f"/api/patients/{p.pk}/visits", body, HTTP_IDEMPOTENCY_KEY=key + "b").status_code == 201
    assert _post(client, f"/api/patients/{p.pk}/visits", body).status_code == 201
    assert Visit.objects.filter(patient=p).count() == 3


@pytest.mark.django_db
def test_a_retry_overlapping_the_first_request_makes_one_visit(client, charlie, clinic, monkeypatch):
    monkeypatch.setattr(api, "IDEMPOTENCY_WAIT_S", 0.5)  # the retry waits, then is told to come back (503)
    key = uuid.uuid4().hex
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin")
    client.force_login(charlie)
    url, body = f"/api/patients/{p.pk}/visits", json.dumps({"date": "2027-01-05", "reason": "brace check"})
    real_create = Visit.objects.create
    answers = []

    def slow_insert(**kw):  # the first's insert waits (SQLite's write lock, a busy database); the client times out
        if not answers:
            answers.append(None)
            answers.append(client.post(url, body, content_type="application/json", HTTP_IDEMPOTENCY_KEY=key))
        return real_create(**kw)

    monkeypatch.setattr(Visit.objects, "create", slow_insert)
    first = client.post(url, body, content_type="application/json", HTTP_IDEMPOTENCY_KEY=key)
    retry = answers[1]
    n = Visit.objects.filter(patient=p).count()
    assert n == 1, f"one key made {n} visits (answers {first.status_code}, {retry.status_code})"
    assert (first.status_code, retry.status_code) == (201, 503) and "Retry-After" in retry
    again = client.post(url, body, content_type="application/json", HTTP_IDEMPOTENCY_KEY=key)
    assert again.status_code == 200 and again.json() == first.json()


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
    monkeypatch.undo()
    made = Patient.objects.get(identifier="P-7")
    assert r.status_code == 409 and f"'P-7' already exists" in r.json()["detail"], r.status_code
    assert f"(id {made.pk})" in r.json()["detail"]  # the client goes on with it
