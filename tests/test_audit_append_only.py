"""The audit trail is append-only: the ORM refuses to change or delete an event, one by one or in bulk."""

import pytest
from django.db import IntegrityError, transaction

from clinic.models import AuditEvent, AuditTrailError


@pytest.mark.django_db
def test_it_refuses_to_update_or_delete_an_audit_event(charlie):
    e = AuditEvent.objects.create(action=AuditEvent.VIEW, user=charlie, username="charlie", patient_id=7)
    e.patient_id = 8
    with pytest.raises(AuditTrailError):
        e.save()
    with pytest.raises(AuditTrailError):
        e.delete()
    with pytest.raises(AuditTrailError):
        AuditEvent.objects.filter(pk=e.pk).update(patient_id=8)
    with pytest.raises(AuditTrailError):
        AuditEvent.objects.filter(pk=e.pk).delete()
    copy = AuditEvent(pk=e.pk, action=AuditEvent.DELETE)  # a new object with an existing key: an insert, refused
    with pytest.raises(IntegrityError), transaction.atomic():
        copy.save()
    assert AuditEvent.objects.get(pk=e.pk).patient_id == 7
    assert AuditEvent.objects.get(pk=e.pk).action == AuditEvent.VIEW


@pytest.mark.django_db
def test_it_keeps_a_deleted_users_events_with_their_name(charlie):
    AuditEvent.objects.create(action=AuditEvent.VIEW, user=charlie, username="charlie", patient_id=7)
    charlie.delete()
    e = AuditEvent.objects.get()
    assert (e.user, e.username, e.patient_id) == (None, "charlie", 7)
