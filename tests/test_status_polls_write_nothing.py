"""A rig (or a page) polling its session's or job's status writes nothing to the database after its first poll:
the audit trail records the view once per caller and object in ``POLL_SECONDS``, the rig key's "last used"
once a minute. Counted as the INSERT, UPDATE and DELETE statements each poll runs."""

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext

from clinic import audit
from clinic.models import AuditEvent, CaptureSession, Job, Patient, Visit
from tests.api_helpers import auth, open_session, small_bundle

WRITES = ("INSERT", "UPDATE", "DELETE")


def writes_of(client, path, **extra):
    with CaptureQueriesContext(connection) as queries:
        r = client.get(path, **extra)
    assert r.status_code == 200, r.content
    return [q["sql"] for q in queries if q["sql"].lstrip().upper().startswith(WRITES)]


@pytest.fixture
def polled(client, small_rig, clinic, tmp_path):
    """(rig key, session id, job id) of a patient's torso session with its job."""
    rig, key = small_rig
    visit = Visit.objects.create(patient=Patient.objects.create(clinic=clinic, identifier="P-1", name="Pat"))
    sid = open_session(client, key, small_bundle(tmp_path), visit=visit.pk).json()["id"]
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=CaptureSession.objects.get(uid=sid))
    return key, sid, str(job.uid)


@pytest.mark.django_db
def test_a_rigs_status_polls_write_nothing_after_the_first(client, polled):
    key, sid, job = polled
    for path in (f"/api/sessions/{sid}", f"/api/jobs/{job}"):
        writes_of(client, path, **auth(key))  # the first poll of each is recorded
        for _ in range(5):
            assert writes_of(client, path, **auth(key)) == [], f"a poll of {path} wrote"
    assert AuditEvent.objects.filter(action=AuditEvent.VIEW, rig_serial="RIG-T").count() == 2


@pytest.mark.django_db
def test_a_poll_is_recorded_again_after_the_interval(client, polled, monkeypatch):
    key, sid, _ = polled
    writes_of(client, f"/api/sessions/{sid}", **auth(key))
    monkeypatch.setattr(audit, "POLL_SECONDS", 0)
    writes_of(client, f"/api/sessions/{sid}", **auth(key))
    assert AuditEvent.objects.filter(action=AuditEvent.VIEW, object_type="capturesession").count() == 2
