"""A clinic deleted with its rigs, jobs and patients' records: the deletion commits (its own audit events name the
clinic while it cascades) and the audit trail keeps the clinic's id, as it keeps an erased patient's."""

import pytest
from django.db import transaction

from clinic.models import AuditEvent, Clinic, Job, Patient, Rig
from tests.patient_records import patient_with_records


@pytest.mark.django_db(transaction=True)
def test_it_deletes_a_clinic_and_keeps_its_audit_trail(clinic):
    patient, _, _ = patient_with_records(clinic)
    cid, pid = clinic.pk, patient.pk
    with transaction.atomic():  # committed: SQLite and PostgreSQL check the foreign keys here
        Job.objects.filter(rig__clinic=clinic).delete()
        Rig.objects.filter(clinic=clinic).delete()
        clinic.delete()
    assert not Clinic.objects.filter(pk=cid).exists() and not Patient.objects.filter(pk=pid).exists()
    trail = AuditEvent.objects.filter(clinic_id=cid, patient_id=pid)
    assert trail.filter(action=AuditEvent.DELETE).exists()
