"""A patient's records and the stored files rows refer to: what an export, an erasure and a backup take.

Files live in Django's default storage; rows name them in their FileFields
and, for pictures, in a ``pictures`` JSON object (picture name -> storage name).
"""

import hashlib
import json

from django.apps import apps
from django.contrib.admin.models import LogEntry
from django.contrib.contenttypes.models import ContentType
from django.core import serializers
from django.core.files.storage import default_storage
from django.core.serializers.json import DjangoJSONEncoder
from django.db import models, transaction
from django.db.models import Q

from . import audit
from .models import (ArmTask, AuditEvent, CaptureImage, CaptureSession, Comparison, Job, Patient, Reconstruction,
                     Visit)

CHUNK = 1 << 20


class ErasureRefused(Exception):
    pass


def patient_records(patient):
    """Every row of ``patient``'s data, as querysets keyed by what they hold (parents before children)."""
    sessions = CaptureSession.objects.filter(visit__patient=patient)
    jobs = Job.objects.filter(session__in=sessions)
    reconstructions = Reconstruction.objects.filter(session__in=sessions)
    return {
        "patient": Patient.objects.filter(pk=patient.pk),
        "visits": Visit.objects.filter(patient=patient),
        "sessions": sessions,
        "images": CaptureImage.objects.filter(session__in=sessions),
        "jobs": jobs,
        "arm_tasks": ArmTask.objects.filter(job__in=jobs),
        "reconstructions": reconstructions,
        # a comparison is the patient's if either torso is (both are, in practice)
        "comparisons": Comparison.objects.filter(Q(later__in=reconstructions) | Q(earlier__in=reconstructions)),
    }


def stored_names(rows):
    """The storage names ``rows`` refer to (file fields and pictures)."""
    names = set()
    for row in rows:
        for field in row._meta.fields:
            if isinstance(field, models.FileField) and getattr(row, field.name):
                names.add(getattr(row, field.name).name)
        names.update(name for name in (getattr(row, "pictures", None) or {}).values() if name)
    return names


def refers_to_files(model):
    return any(isinstance(f, models.FileField) for f in model._meta.fields) or any(
        f.name == "pictures" for f in model._meta.fields)


def all_stored_names():
    """Every storage name any row of the clinic's records refers to."""
    names = set()
    for model in apps.get_app_config("clinic").get_models():
        if refers_to_files(model):
            names |= stored_names(model.objects.all().iterator())
    return names


def sha256_of_stored(name):
    digest = hashlib.sha256()
    with default_storage.open(name, "rb") as fh:
        for chunk in iter(lambda: fh.read(CHUNK), b""):
            digest.update(chunk)
    return digest.hexdigest()


def as_json(records) -> str:
    """``records`` (name -> queryset) as one JSON document of Django's serialization (model, pk, fields)."""
    return json.dumps({key: serializers.serialize("python", qs.order_by("pk")) for key, qs in records.items()},
                      cls=DjangoJSONEncoder, indent=1)


def running_jobs(patient):
    return Job.objects.filter(session__visit__patient=patient, state__in=[Job.QUEUED, Job.RUNNING])


def erase(patient, *, username=""):
    """Delete every row and stored file of ``patient``; one "erase" audit event says what went.

    Returns ``(counts, files not deleted)``. Refused while a job of the
    patient is queued or running: it would write results for rows that are gone.
    The rows go in one transaction; the files after it committed, and only
    those no remaining row refers to (no stored file is deleted while a row
    points to it).
    """
    busy = list(running_jobs(patient).values_list("uid", "state"))
    if busy:
        raise ErasureRefused(f"patient {patient.pk} has {len(busy)} job(s) not finished ("
                             + ", ".join(f"{uid} {state}" for uid, state in busy)
                             + "): wait until they succeed or fail, then erase again")
    patient_id, clinic_id = patient.pk, patient.clinic_id
    with transaction.atomic(), audit.quiet():
        records = patient_records(patient)
        files = stored_names(row for qs in records.values() for row in qs)
        counts = {key: qs.count() for key, qs in records.items()}
        # the admin's history names the objects it changed (a patient's name among them): it goes too
        for qs in records.values():
            LogEntry.objects.filter(content_type=ContentType.objects.get_for_model(qs.model),
                                    object_id__in=[str(pk) for pk in qs.values_list("pk", flat=True)]).delete()
        records["comparisons"].delete()
        records["sessions"].delete()  # with their images, jobs, arm tasks and reconstructions
        patient.delete()  # with the visits
        doomed = files - all_stored_names()
        counts["files"] = len(doomed)
        audit.record(AuditEvent.ERASE, username=username, patient_id=patient_id, clinic_id=clinic_id,
                     object_type="patient", object_id=patient_id, detail={"rows": counts})
    kept = []
    for name in sorted(doomed):
        try:
            default_storage.delete(name)
        except OSError:
            kept.append(name)
    return counts, kept
