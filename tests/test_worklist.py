"""The home page opens with the worklist: today's visits and the patients whose follow-up is overdue, within the
user's clinics only."""

from datetime import date, timedelta

import pytest
from django.utils import timezone

from clinic.models import Patient, Visit
from clinic.views import months_before


def _patient(clinic, ident, *visits):
    """A patient with visits given as ``(date, next visit due or None)``."""
    p = Patient.objects.create(clinic=clinic, identifier=ident, name=f"Patient {ident}")
    for day, due in visits:
        Visit.objects.create(patient=p, date=day, next_visit_due=due)
    return p


@pytest.mark.django_db
def test_the_worklist_lists_today_and_the_overdue_in_the_users_clinics(client, charlie, olga, nobody, clinic,
                                                                       other_clinic):
    today = timezone.localdate()
    _patient(clinic, "TODAY", (today - timedelta(days=400), None), (today, None))
    _patient(clinic, "DUE-PASSED", (today - timedelta(days=100), today - timedelta(days=3)))
    _patient(clinic, "DUE-LATER", (today - timedelta(days=300), today + timedelta(days=30)))  # a long interval set
    _patient(clinic, "OLD", (today - timedelta(days=300), None))  # no date set: six months
    _patient(clinic, "RECENT", (today - timedelta(days=60), None))
    _patient(clinic, "BOOKED", (today - timedelta(days=400), None), (today + timedelta(days=7), None))
    _patient(clinic, "NEVER-SEEN")
    _patient(other_clinic, "ELSEWHERE", (today, None), (today - timedelta(days=1), today - timedelta(days=1)))

    client.force_login(charlie)
    w = client.get("/").context["worklist"]
    assert [v.patient.identifier for v in w["visits_today"]] == ["TODAY"]
    assert [r["identifier"] for r in w["overdue"]] == ["OLD", "DUE-PASSED"]  # the longest overdue first
    html = client.get("/").content.decode()
    assert "Worklist for" in html and "Patient TODAY" in html and "more than 6 months ago" in html

    client.force_login(olga)  # the other clinic sees its own patient only
    w = client.get("/").context["worklist"]
    assert [v.patient.identifier for v in w["visits_today"]] == ["ELSEWHERE"]
    assert [r["identifier"] for r in w["overdue"]] == []  # its latest visit is today's
    client.force_login(nobody)
    w = client.get("/").context["worklist"]
    assert not w["visits_today"] and not w["overdue"]


@pytest.mark.django_db
def test_the_follow_up_interval_is_a_setting(client, charlie, clinic, settings):
    today = timezone.localdate()
    _patient(clinic, "OLD", (today - timedelta(days=100), None))
    client.force_login(charlie)
    assert client.get("/").context["worklist"]["overdue"] == []
    settings.FOLLOW_UP_MONTHS = 3
    assert [r["identifier"] for r in client.get("/").context["worklist"]["overdue"]] == ["OLD"]


def test_months_are_counted_on_the_calendar():
    assert months_before(date(2026, 8, 31), 6) == date(2026, 2, 28)
    assert months_before(date(2026, 1, 15), 1) == date(2025, 12, 15)
    assert months_before(date(2026, 1, 15), -6) == date(2026, 7, 15)


@pytest.mark.django_db
def test_a_visit_sets_when_the_next_one_is_due_and_its_notes_are_edited(client, charlie, clinic):
    from clinic.models import AuditEvent

    p = _patient(clinic, "P-1", ("2026-07-01", None))
    v = p.visits.get()
    client.force_login(charlie)
    r = client.post(f"/visits/{v.pk}/edit", {"date": "2026-07-01", "next_visit_due": "2026-06-01"})
    assert r.status_code == 400 and "must be due after this visit" in r.content.decode()
    r = client.post(f"/visits/{v.pk}/edit", {"date": "2026-07-01", "notes": "x" * 20_001})
    assert r.status_code == 400 and "at most 20000 characters" in r.content.decode()
    r = client.post(f"/visits/{v.pk}/edit", {"date": "2026-07-01", "next_visit_due": "2027-01-01",
                                             "notes": "Brace 20 h a day"})
    v.refresh_from_db()
    assert r.status_code == 302 and str(v.next_visit_due) == "2027-01-01" and v.notes == "Brace 20 h a day"
    assert "Next visit due on 1 Jan 2027" in client.get(f"/visits/{v.pk}/").content.decode()
    # the change is in the audit trail, under the patient
    assert AuditEvent.objects.filter(action=AuditEvent.CHANGE, object_type="visit", patient_id=p.pk,
                                     username="charlie").exists()
    r = client.post(f"/patients/{p.pk}/edit", {"identifier": "P-1", "name": "Patient P-1", "notes": "y" * 20_001})
    assert r.status_code == 400 and "at most 20000 characters" in r.content.decode()
    r = client.post(f"/patients/{p.pk}/edit", {"identifier": "P-1", "name": "Patient P-1", "notes": "Risser 2"})
    p.refresh_from_db()
    assert r.status_code == 302 and p.notes == "Risser 2"
    assert AuditEvent.objects.filter(action=AuditEvent.CHANGE, object_type="patient", patient_id=p.pk).exists()
