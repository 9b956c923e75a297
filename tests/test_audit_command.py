"""manage.py audit lists the trail by patient, user and date."""

import json
from datetime import datetime, timezone
from io import StringIO

import pytest
from django.core.management import call_command

from clinic.models import AuditEvent


def _audit(*args):
    out = StringIO()
    call_command("audit", *args, stdout=out)
    return out.getvalue()


@pytest.mark.django_db
def test_it_lists_only_the_named_patients_events(charlie, alice):
    day = lambda d: datetime(2026, 11, d, 10, tzinfo=timezone.utc)  # noqa: E731
    AuditEvent.objects.create(time=day(1), action=AuditEvent.VIEW, user=charlie, username="charlie", patient_id=1,
                              object_type="patient", object_id="1", path="/patients/1/", method="GET", status=200)
    AuditEvent.objects.create(time=day(2), action=AuditEvent.VIEW, user=charlie, username="charlie", patient_id=2,
                              object_type="patient", object_id="2", path="/patients/2/", method="GET", status=200)
    AuditEvent.objects.create(time=day(3), action=AuditEvent.CHANGE, user=alice, username="alice", patient_id=1,
                              object_type="visit", object_id="5", path="/visits/5/edit", method="POST", status=302)

    rows = json.loads(_audit("--patient", "1", "--json"))
    assert [(r["patient"], r["user"], r["action"], r["path"]) for r in rows] == [
        (1, "charlie", "view", "/patients/1/"), (1, "alice", "change", "/visits/5/edit")]
    text = _audit("--patient", "2")
    assert "/patients/2/" in text and "/patients/1/" not in text and "1 event(s)" in text

    assert [r["patient"] for r in json.loads(_audit("--user", "charlie", "--json"))] == [1, 2]
    assert [r["patient"] for r in json.loads(_audit("--since", "2026-11-02", "--until", "2026-11-02", "--json"))] == [2]
    assert [r["user"] for r in json.loads(_audit("--patient", "1", "--since", "2026-11-02", "--json"))] == ["alice"]
