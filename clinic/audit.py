"""The audit trail: who viewed, downloaded, created, changed or deleted which patient's data, when, from where.

Three sources write :class:`~clinic.models.AuditEvent` rows, the application
never changes or deletes one:

- :class:`AuditMiddleware`, after each response: a request whose URL names a
  patient or one of a patient's records (pages, the API, the admin) by a
  signed-in user or a rig's key is a view, or a download (the API's result
  files); a write that the model signals below did not see (a re-run, an
  image upload, a refused form) is recorded as the attempt it was, with its
  status;
- ``post_save`` / ``post_delete`` of patients' records: create, change,
  delete, by the user of the request being answered (nobody for a job or a
  command, which run outside any request);
- sign-ins and failed sign-ins (the pages' and the admin's).

The request being answered travels in a context variable, so the model
signals know who acts without the views passing it down.
"""

import contextlib
import contextvars
import ipaddress
import logging
import uuid

from celery.signals import task_postrun, task_prerun
from django.conf import settings
from django.contrib.auth.signals import user_logged_in, user_login_failed
from django.core.exceptions import ValidationError
from django.db import DatabaseError, transaction
from django.db.models.signals import post_delete, post_save
from django.dispatch import receiver

from .models import (ArmTask, AuditEvent, CaptureImage, CaptureSession, Comparison, Job, Patient, Reconstruction,
                     Visit)

log = logging.getLogger(__name__)

# How each kind of record reaches its patient (None: the record is the patient).
PATIENT_PATHS = {
    Patient: None,
    Visit: "patient",
    CaptureSession: "visit__patient",
    CaptureImage: "session__visit__patient",
    Job: "session__visit__patient",
    ArmTask: "job__session__visit__patient",
    Reconstruction: "session__visit__patient",
    Comparison: "later__session__visit__patient",
}
# Status polls (the API's session and job status, which a rig or a page asks for every few seconds) are
# recorded once per caller and object in this many seconds: a poll that finds its view already recorded writes
# nothing. Every other view is recorded each time.
POLLS = {("api", "session_status"), ("api", "job_status")}
POLL_SECONDS = 600

# Their saves and deletions are recorded (jobs, images and arm tasks change through queryset updates, which send
# no signal; the middleware records the requests that cause them).
SIGNALLED = (Patient, Visit, CaptureSession, Reconstruction, Comparison)


class _Current:
    """The request being answered, and whether a model signal already recorded what it did."""

    def __init__(self, request):
        self.request = request
        self.recorded = 0


_current = contextvars.ContextVar("audit_request", default=None)
_quiet = contextvars.ContextVar("audit_quiet", default=False)


@contextlib.contextmanager
def quiet():
    """Record no per-row events inside (an erasure records one event for the whole patient)."""
    token = _quiet.set(True)
    try:
        yield
    finally:
        _quiet.reset(token)


def patient_of_row(model, **lookup):
    """``(patient id, clinic id)`` of the ``model`` row matching ``lookup``, or ``(None, None)``."""
    path = PATIENT_PATHS[model]
    prefix = f"{path}__" if path else ""
    try:
        row = model.objects.filter(**lookup).values_list(f"{prefix}id", f"{prefix}clinic_id").first()
    except (ValueError, ValidationError):  # an id that is not one (the view answers 404)
        return None, None
    return row or (None, None)


def patient_of(instance):
    """``(patient id, clinic id)`` of a record; works in ``post_delete`` too (from the record's own foreign key)."""
    model = type(instance)
    path = PATIENT_PATHS[model]
    if path is None:
        return instance.pk, instance.clinic_id
    first = path.split("__")[0]
    parent_id = getattr(instance, f"{first}_id")
    if parent_id is None:  # e.g. a test-field session: no patient's data
        return None, None
    return patient_of_row(model._meta.get_field(first).related_model, pk=parent_id)


def remote_addr(request):
    """The client's address; behind the TLS proxy (SECURE_PROXY_SSL_HEADER set) the one that proxy appended."""
    addr = request.META.get("REMOTE_ADDR", "")
    if getattr(settings, "SECURE_PROXY_SSL_HEADER", None) and request.META.get("HTTP_X_FORWARDED_FOR"):
        # the last entry is the proxy's own; earlier ones come from the client and could be forged
        addr = request.META["HTTP_X_FORWARDED_FOR"].split(",")[-1].strip()
    try:
        return str(ipaddress.ip_address(addr))
    except ValueError:
        return None


def record(action, *, request=None, user=None, username="", patient_id=None, clinic_id=None, object_type="",
           object_id="", status=None, detail=None):
    """Append one event; the acting user and rig come from ``request`` (default: the request being answered).

    A trail that cannot be written is logged, not raised: the database being
    down must not turn the API's 503 (retry) into a 500.
    """
    current = _current.get()
    if request is None and current is not None:
        request = current.request
    rig = getattr(request, "rig", None) if request is not None else None
    if user is None and request is not None and getattr(request, "user", None) is not None \
            and request.user.is_authenticated:
        user = request.user
    if clinic_id is None and rig is not None:
        clinic_id = rig.clinic_id
    event = AuditEvent(
        action=action, user=user, username=(user.get_username() if user else username)[:150],
        rig_serial=rig.serial if rig is not None else "", clinic_id=clinic_id, patient_id=patient_id,
        object_type=object_type, object_id=str(object_id or "")[:64], status=status, detail=detail or {},
        path=request.path[:500] if request is not None else "", method=(request.method or "") if request is not None else "",
        remote_addr=remote_addr(request) if request is not None else None)
    try:
        with transaction.atomic():  # a savepoint: a failed insert leaves the caller's transaction usable
            event.save()
    except DatabaseError:
        log.exception("could not record the audit event %s %s %s", action, object_type, object_id)
        return None
    if current is not None and current.request is request:
        current.recorded += 1
    return event


# --- requests -------------------------------------------------------------------------------------------------------

def _by_uid_or_pk(model, value):
    try:
        return patient_of_row(model, uid=uuid.UUID(str(value)))
    except ValueError:
        pass
    return patient_of_row(model, pk=int(value)) if str(value).isdigit() else (None, None)


def target(match):
    """``(object type, object id, patient id, clinic id)`` named by a resolved URL, or None."""
    kw = match.kwargs
    if "patient_id" in kw:
        return ("patient", kw["patient_id"], *patient_of_row(Patient, pk=kw["patient_id"]))
    if "visit_id" in kw:
        return ("visit", kw["visit_id"], *patient_of_row(Visit, pk=kw["visit_id"]))
    if "session_id" in kw:
        return ("capturesession", kw["session_id"], *_by_uid_or_pk(CaptureSession, kw["session_id"]))
    if "job_id" in kw:
        return ("job", kw["job_id"], *_by_uid_or_pk(Job, kw["job_id"]))
    if "pk" in kw and kw.get("kind") in ("reconstruction", "comparison"):
        model = Reconstruction if kw["kind"] == "reconstruction" else Comparison
        return (kw["kind"], kw["pk"], *patient_of_row(model, pk=kw["pk"]))
    if match.namespace == "admin" and "object_id" in kw and (match.url_name or "").startswith("clinic_"):
        # the admin's clinic_<model>_<change|delete|history> pages
        model_name = match.url_name[len("clinic_"):].rsplit("_", 1)[0]
        for model in PATIENT_PATHS:
            if model._meta.model_name == model_name:
                found = patient_of_row(model, pk=kw["object_id"]) if str(kw["object_id"]).isdigit() else (None, None)
                return (model_name, kw["object_id"], *found)
    return None


def record_request(request, response, current):
    match = getattr(request, "resolver_match", None)
    if match is None:
        return
    user = getattr(request, "user", None)
    if not (user is not None and user.is_authenticated) and getattr(request, "rig", None) is None:
        return  # nobody was let in: the failed sign-ins are recorded by the signal below
    if request.method in ("GET", "HEAD"):
        action = AuditEvent.DOWNLOAD if (match.namespace == "api" and match.url_name == "job_file") \
            else AuditEvent.VIEW
    elif current.recorded:
        return  # the model signals recorded what the write did
    else:
        action = AuditEvent.DELETE if request.method == "DELETE" else AuditEvent.CHANGE
    found = target(match)
    if found is None:
        return
    object_type, object_id, patient_id, clinic_id = found
    if patient_id is None and object_type != "patient":
        return  # a calibration job, a test-field session: no patient's data
    if (match.namespace, match.url_name) in POLLS and _polled_recently(request, object_type, object_id):
        return
    record(action, request=request, patient_id=patient_id, clinic_id=clinic_id, object_type=object_type,
           object_id=object_id, status=response.status_code)


def _polled_recently(request, object_type, object_id) -> bool:
    """Whether the same caller's view of the same object was recorded in the last POLL_SECONDS (a read)."""
    from datetime import timedelta

    from django.utils import timezone

    rig = getattr(request, "rig", None)
    who = {"rig_serial": rig.serial, "user": None} if rig is not None else {"user": request.user}
    return AuditEvent.objects.filter(action=AuditEvent.VIEW, object_type=object_type, object_id=str(object_id),
                                     time__gte=timezone.now() - timedelta(seconds=POLL_SECONDS), **who).exists()


class AuditMiddleware:
    """Makes the request known to the model signals, and records views and downloads of patients' data.

    Place it after AuthenticationMiddleware (it needs ``request.user``).
    """

    def __init__(self, get_response):
        self.get_response = get_response

    def __call__(self, request):
        current = _Current(request)
        token = _current.set(current)
        try:
            response = self.get_response(request)
        finally:
            _current.reset(token)
        try:
            record_request(request, response, current)
        except DatabaseError:  # e.g. looking up the patient while the database is down: the answer stands
            log.exception("could not audit %s %s", request.method, request.path)
        return response


# --- records ----------------------------------------------------------------------------------------------------------

def _saved(sender, instance, created, raw=False, **kwargs):
    if raw or _quiet.get():  # raw: loaddata (a restore) replays rows, nobody changes them
        return
    patient_id, clinic_id = patient_of(instance)
    if patient_id is None:
        return
    record(AuditEvent.CREATE if created else AuditEvent.CHANGE, patient_id=patient_id, clinic_id=clinic_id,
           object_type=sender._meta.model_name, object_id=instance.pk,
           detail={"fields": sorted(kwargs["update_fields"])} if kwargs.get("update_fields") else None)


def _deleted(sender, instance, **kwargs):
    if _quiet.get():
        return
    patient_id, clinic_id = patient_of(instance)
    if patient_id is None:
        return
    record(AuditEvent.DELETE, patient_id=patient_id, clinic_id=clinic_id, object_type=sender._meta.model_name,
           object_id=instance.pk)


for _model in SIGNALLED:
    post_save.connect(_saved, sender=_model, dispatch_uid=f"audit-save-{_model._meta.model_name}")
    post_delete.connect(_deleted, sender=_model, dispatch_uid=f"audit-delete-{_model._meta.model_name}")


# --- jobs act for nobody ------------------------------------------------------------------------------------------

# A task run in-process (no broker) runs inside the request that queued it; what it writes is the job's doing,
# not the requester's, as it would be on a worker.
_task_tokens = {}


@task_prerun.connect(dispatch_uid="audit-task-prerun")
def _task_starts(task_id=None, **kwargs):
    _task_tokens[task_id] = _current.set(None)


@task_postrun.connect(dispatch_uid="audit-task-postrun")
def _task_ends(task_id=None, **kwargs):
    token = _task_tokens.pop(task_id, None)
    if token is not None:
        try:
            _current.reset(token)
        except ValueError:  # set in another context (cannot happen with Celery's own pools): just forget it
            _current.set(None)


# --- sign-ins ---------------------------------------------------------------------------------------------------------

@receiver(user_logged_in, dispatch_uid="audit-login")
def _logged_in(sender, request=None, user=None, **kwargs):
    record(AuditEvent.LOGIN, request=request, user=user)


@receiver(user_login_failed, dispatch_uid="audit-login-failed")
def _login_failed(sender, credentials=None, request=None, **kwargs):
    record(AuditEvent.LOGIN_FAILED, request=request, username=str((credentials or {}).get("username") or ""))
