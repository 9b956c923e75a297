"""The JSON API: the rig uploads its captures; staff register rigs, patients and visits.

OpenAPI at ``/api/openapi.json`` (browsable at ``/api/docs``). A rig
authenticates with ``Authorization: Bearer <key>``; staff with their login
session. Every query is scoped to what the caller may see: anything else is
a 404, as if it did not exist.

Images are streamed to storage in chunks while their sha256 is computed;
nothing is held whole in memory and nothing is kept unless it checks out.
Nothing is acknowledged before everything it refers to is stored, and no
stored file is deleted while a row points to it: when the database or the
storage fails, the answer is 503 with ``Retry-After``, and the retry finishes
the upload.
"""

import contextlib
import hashlib
import json
import logging
import os
import secrets
import struct
import tempfile
import zipfile
import zlib
import datetime as dt
from pathlib import Path, PurePosixPath
from typing import Annotated, Literal, Optional

from django.conf import settings
from django.core.exceptions import RequestDataTooBig
from django.core.files import File
from django.core.files.storage import default_storage
from django.db import DatabaseError, IntegrityError, InterfaceError, OperationalError, connection, transaction
from django.http import FileResponse
from django.shortcuts import get_object_or_404
from django.utils import timezone
from ninja import NinjaAPI, Schema
from ninja import Path as PathParam
from pydantic import Field, field_validator
from ninja.security import HttpBearer, django_auth

from recon_engine.formats import FormatError, check_zip_members, decode_image, parse_capture_manifest, rig_from_dict

from . import once, pipeline
from .imageheaders import HeaderError, image_size
from .validation import (MAX_ID, MAX_INTERVAL_DAYS, MAX_NOTES, MAX_POSES, DbId, Invalid, check_capture, check_json,
                         check_length, check_param, check_rig, text)
from .models import (CaptureImage, CaptureSession, Clinic, Job, Member, Patient, Reconstruction, Rig, RigKey,
                     TestField, Visit, captures_of, clinics_of, image_path, jobs_of)

CHUNK = 1 << 20
RETRY_AFTER_SECONDS = 30  # what a 503 asks the rig to wait before retrying
KEY_USE_RESOLUTION = dt.timedelta(minutes=1)  # how stale a rig key's "last used" may be
MAX_BUNDLE_MEMBERS = 1000  # a capture holds a manifest and one image per camera; a zip's directory is parsed whole

log = logging.getLogger(__name__)


class ApiError(Exception):
    def __init__(self, status: int, detail: str):
        super().__init__(detail)
        self.status, self.detail = status, detail


class Unavailable(ApiError):
    """Something the upload needs is briefly down: nothing was acknowledged, the same request may be retried."""

    def __init__(self, detail: str):
        super().__init__(503, detail + f"; nothing was acknowledged: retry in {RETRY_AFTER_SECONDS} s")


class RigKeyAuth(HttpBearer):
    def authenticate(self, request, token):
        key = RigKey.lookup(token)
        if key is None:
            return None
        now = timezone.now()
        # "last used" to the minute: a rig polling its job every second must not write on every poll
        if key.last_used is None or now - key.last_used >= KEY_USE_RESOLUTION:
            RigKey.objects.filter(pk=key.pk).update(last_used=now)
        request.rig = key.rig
        return key.rig


api = NinjaAPI(title="torsoscan", version="1", urls_namespace="api",
               description="The rig's upload API and the clinic's records. Files follow capture-format.md.")


@api.exception_handler(ApiError)
def _api_error(request, exc):
    response = api.create_response(request, {"detail": exc.detail}, status=exc.status)
    if exc.status == 503:
        response["Retry-After"] = str(RETRY_AFTER_SECONDS)
    return response


@api.exception_handler(OperationalError)
@api.exception_handler(InterfaceError)
def _database_down(request, exc):
    log.warning("database unreachable during %s %s: %s", request.method, request.path, exc)
    return _api_error(request, Unavailable("the database is unreachable"))


@api.exception_handler(FormatError)
@api.exception_handler(Invalid)
def _format_error(request, exc):
    return api.create_response(request, {"detail": str(exc)}, status=400)


@api.exception_handler(RequestDataTooBig)
def _body_too_big(request, exc):
    # a JSON body is read whole into memory: Django's DATA_UPLOAD_MAX_MEMORY_SIZE bounds it
    return api.create_response(request, {"detail": f"the request body is larger than "
                                                   f"{settings.DATA_UPLOAD_MAX_MEMORY_SIZE} bytes"}, status=413)


@api.exception_handler(Exception)
def _internal_error(request, exc):
    """A defect, not bad input: logged with its traceback under an id the answer gives, so a report finds it."""
    error_id = secrets.token_hex(4)
    log.error("internal error %s during %s %s", error_id, request.method, request.path, exc_info=exc)
    return api.create_response(request, {"detail": "internal error", "id": error_id}, status=500)


def _respond(request, data, status=200):
    return api.create_response(request, data, status=status)


# --- schemas ---------------------------------------------------------------------------

# Every field is bounded here, as its column is (clinic/models.py), so the OpenAPI shows the limits and a
# value past them is a 422 naming the field before the database sees it.
CalibrationSet = text(100, min_length=1)
Poses = Annotated[int, Field(ge=1, le=MAX_POSES)]


class SessionIn(Schema):
    manifest: dict  # capture.json
    visit: Optional[DbId] = None  # torso sessions: the visit they belong to
    calibration_set: Optional[CalibrationSet] = None  # test-field sessions calibrated together (default: the date)
    poses: Optional[Poses] = None  # how many test-field poses the set holds (default: the rig's setting)


class RigIn(Schema):
    clinic: DbId
    rig: dict  # rig.json
    recalibration_interval_days: Annotated[int, Field(ge=1, le=MAX_INTERVAL_DAYS)] = 30
    poses_per_calibration: Poses = 3


class TestFieldIn(Schema):
    clinic: DbId
    testfield: dict  # testfield.json


def _not_in_future(value: Optional[dt.date], what: str) -> Optional[dt.date]:
    if value is not None and value > timezone.localdate():
        raise ValueError(f"{what} {value} is in the future")
    return value


class PatientIn(Schema):
    clinic: DbId
    identifier: text(64, min_length=1, strip=True)
    name: text(200, min_length=1, strip=True)
    date_of_birth: Optional[dt.date] = None
    sex: Literal["", "F", "M", "X"] = ""  # female, male, other / not stated
    notes: text(MAX_NOTES) = ""

    @field_validator("date_of_birth")
    @classmethod
    def _born_in_the_past(cls, value):
        return _not_in_future(value, "date of birth")


class VisitIn(Schema):
    date: Optional[dt.date] = None
    reason: text(200) = ""
    notes: text(MAX_NOTES) = ""


# --- helpers ------------------------------------------------------------------------------

def member_clinic(request, clinic_id, roles=(Member.ADMINISTRATOR, Member.TECHNICIAN)):
    m = Member.objects.filter(user=request.user, clinic_id=clinic_id).first()
    if m is None:
        raise ApiError(404, f"clinic {clinic_id} not found")
    if m.role not in roles:
        raise ApiError(403, f"a {m.role} cannot do this; ask a clinic {' or '.join(roles)}")
    return m.clinic


def _sessions_for(request):
    """The capture sessions the caller may see: a rig its own, of its clinic's patients; a member its clinics'
    (a patient's scan is its patient's clinic's, :func:`clinic.models.captures_of`)."""
    if getattr(request, "rig", None) is not None:
        rig = request.rig
        return CaptureSession.objects.filter(captures_of(Clinic.objects.filter(pk=rig.clinic_id)), rig=rig)
    return CaptureSession.objects.filter(captures_of(clinics_of(request.user)))


def _jobs_for(request):
    if getattr(request, "rig", None) is not None:
        rig = request.rig
        return Job.objects.filter(jobs_of(Clinic.objects.filter(pk=rig.clinic_id)), rig=rig)
    return Job.objects.filter(jobs_of(clinics_of(request.user)))


def _job_out(job: Job) -> dict:
    out = {"id": str(job.uid), "kind": job.kind, "state": job.state, "stage": job.stage, "percent": job.percent,
           "error": job.error, "attempt": job.attempt,
           "created": job.created.isoformat(), "finished": job.finished.isoformat() if job.finished else None}
    if job.kind == Job.RECONSTRUCTION:
        out["arms"] = {a.arm: {"state": a.state, "error": a.error} for a in job.arms.all()}
        rec = Reconstruction.objects.filter(job=job).first()
        if rec is not None:
            out["result"] = {"status": rec.status, "points": rec.points,
                             "files": [n for n, f in (("torso.ply", rec.torso), ("torso-mesh.ply", rec.mesh),
                                                      ("report.json", rec.report_file)) if f]}
    elif hasattr(job, "calibration_result"):
        out["result"] = {"calibration": job.calibration_result.pk, "files": ["calibration.json"]}
    return out


def _session_out(s: CaptureSession) -> dict:
    images = list(s.images.all())
    return {"id": str(s.uid), "rig": s.rig.serial, "kind": s.kind, "state": s.state,
            "pose": s.pose, "calibration_set": s.calibration_set or None,
            "visit": s.visit_id, "captured_at": s.captured_at,
            "received": sorted(i.camera for i in images if i.file),
            "missing": sorted(i.camera for i in images if not i.file) if s.state == s.OPEN else s.missing_cameras,
            "needs_recalibration": s.needs_recalibration,
            "recalibration_reason": s.rig.recalibration_reason if s.needs_recalibration else "",
            "jobs": [_job_out(j) for j in list(s.jobs.all()) + list(s.calibration_jobs.exclude(session=s))]}


def _canonical_sha256(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _body(request, limit: int, what: str):
    """The raw request body as a stream, refused before it is read when it cannot fit ``limit``.

    A declared Content-Length above the limit is a 413 at once. A chunked body (no Content-Length) is read
    to its end only where the server delimits it (``wsgi.input_terminated``: gunicorn does, and behind nginx
    every request arrives with a Content-Length anyway, nginx having buffered it); elsewhere Django would see
    an empty body, so it is a 411 rather than a misleading "sha256 mismatch" or "not a zip".
    """
    declared = request.META.get("CONTENT_LENGTH", "")
    if declared:
        try:
            length = int(declared)
        except ValueError:
            raise ApiError(400, f"Content-Length {declared!r} is not a number") from None
        if length > limit:
            raise ApiError(413, f"{what} is larger than {limit} bytes (Content-Length {length}); nothing was read")
        return request
    if "chunked" in request.META.get("HTTP_TRANSFER_ENCODING", "").lower():
        if request.META.get("wsgi.input_terminated"):
            return request.META["wsgi.input"]  # read to its end by _spool, at most ``limit`` bytes
        raise ApiError(411, f"{what}: this server cannot read a chunked body; send it with a Content-Length")
    return request  # no body at all: an empty one


def _spool(stream, limit: int, what: str, status: int = 413):
    """Copy a request (or zip member) stream to a temporary file in chunks: (file, sha256, size).

    Counts what it reads, whatever the stream claimed (a zip member's declared size may lie). The server's own
    disk failing (full, say) is a 503: the rig keeps the capture and retries."""
    try:
        tmp = tempfile.NamedTemporaryFile(dir=settings.FILE_UPLOAD_TEMP_DIR, suffix=".part")
    except OSError as exc:
        raise _folder_failed(what, exc) from None
    digest, size = hashlib.sha256(), 0
    while True:
        chunk = stream.read(CHUNK)  # a client that stops sending raises here: not the server's fault
        if not chunk:
            break
        size += len(chunk)
        if size > limit:
            tmp.close()
            raise ApiError(status, f"{what} is larger than {limit} bytes")
        digest.update(chunk)
        try:
            tmp.write(chunk)
        except OSError as exc:
            tmp.close()
            raise _folder_failed(what, exc) from None
    try:
        tmp.flush()
    except OSError as exc:
        tmp.close()
        raise _folder_failed(what, exc) from None
    tmp.seek(0)
    return tmp, digest.hexdigest(), size


def _folder_failed(what: str, exc: OSError) -> "Unavailable":
    """The upload folder failed taking ``what`` (full, say): logged, and a 503 for the rig to retry."""
    log.error("the upload folder failed taking %s: %s", what, exc)
    return Unavailable(f"the server could not take {what} ({exc.strerror or type(exc).__name__})")


def _check_image(tmp, rig, image: CaptureImage, where: str):
    """Refuse a truncated or undecodable image, or one of the wrong size (names the camera).

    The size is read from the header first: only an image of the camera's size is decoded (a small file may
    claim a huge image, and decoding allocates all of it)."""
    spec = rig.cameras.get(image.camera)
    try:
        width, height = image_size(tmp)
    except HeaderError as exc:
        raise ApiError(400, f"{where}: camera {image.camera!r}: {exc}") from None
    if spec is not None and (width, height) != (spec.width, spec.height):
        raise ApiError(400, f"{where}: camera {image.camera!r}: image is {width}x{height} px, "
                            f"rig.json says {spec.width}x{spec.height}")
    tmp.seek(0)
    decode_image(tmp.read(), where, image.camera, PurePosixPath(image.file_name).suffix.lower(), rig)
    tmp.seek(0)


def _idempotency_key(request, manifest: dict) -> str:
    """What identifies a retried request: the rig's ``Idempotency-Key`` header, else the manifest's checksum."""
    key = check_param(request.headers.get("Idempotency-Key", ""), "Idempotency-Key header", 200)
    return key or "manifest:" + _canonical_sha256(manifest)


def _create_session(rig: Rig, body: SessionIn, key: str):
    """(session, created). A retried request (same key or same manifest) finds the first session."""
    engine_rig = rig_from_dict(rig.description, f"rig {rig.serial}")
    capture = parse_capture_manifest(body.manifest, "capture.json", engine_rig)
    check_capture(capture, body.manifest, "capture.json")
    existing = CaptureSession.objects.filter(rig=rig, idempotency_key=key).first()
    if existing is not None:
        if existing.manifest_sha256 != _canonical_sha256(body.manifest):
            raise ApiError(409, f"session {existing.uid} was opened with another capture.json under the same "
                                "Idempotency-Key; send a new key for a new capture")
        return existing, False
    visit = testfield = None
    if capture.kind == "torso":
        if body.visit is not None:
            visit = Visit.objects.filter(pk=body.visit, patient__clinic=rig.clinic).first()
            if visit is None:
                raise ApiError(404, f"visit {body.visit} not found in the rig's clinic")
    else:
        testfield = TestField.objects.filter(clinic=rig.clinic, name=capture.testfield).first()
        if testfield is None:
            raise ApiError(400, f"capture.json: test field {capture.testfield!r} is not registered for "
                                f"{rig.clinic.name}")
        calibration_set = body.calibration_set or capture.captured_at[:10]
        done = Job.objects.filter(kind=Job.CALIBRATION, rig=rig, sessions__calibration_set=calibration_set).first()
        if done is not None:
            # the set's poses were calibrated (or failed to) already: a pose added now would start nothing
            raise ApiError(409, f"calibration set {calibration_set!r} of rig {rig.serial} was already calibrated "
                                f"(job {done.uid}, {done.state}); send the new poses under a new calibration_set")
    try:
        with transaction.atomic():
            session = CaptureSession.objects.create(
                rig=rig, kind=capture.kind, visit=visit, testfield=testfield, pose=capture.pose,
                calibration_set=(body.calibration_set or capture.captured_at[:10]) if testfield else "",
                poses_expected=body.poses if testfield else None,
                manifest=body.manifest, manifest_sha256=_canonical_sha256(body.manifest), idempotency_key=key,
                captured_at=capture.captured_at, needs_recalibration=rig.needs_recalibration)
            CaptureImage.objects.bulk_create(
                CaptureImage(session=session, camera=im.camera, file_name=im.file, sha256=im.sha256)
                for im in capture.images)
    except IntegrityError:  # the same retry raced us: the first one won
        return CaptureSession.objects.get(rig=rig, idempotency_key=key), False
    return session, True


def _finalize(session: CaptureSession, partial: bool) -> CaptureSession:
    with transaction.atomic():
        s = CaptureSession.objects.select_for_update().get(pk=session.pk)
        if s.state != s.OPEN:
            raise ApiError(409, f"session {s.uid} is already finalized ({s.state})")
        missing = sorted(s.images.filter(file="").values_list("camera", flat=True))
        if missing and not partial:
            raise ApiError(409, f"session {s.uid}: no image yet for cameras {', '.join(missing)}; upload them "
                                "or finalize with partial=true")
        if len(missing) == s.images.count():
            raise ApiError(409, f"session {s.uid}: no image was received")
        engine_rig = rig_from_dict(s.rig.description, f"rig {s.rig.serial}")
        absent = [c for c in engine_rig.camera_ids if c not in {e["camera"] for e in s.manifest["images"]}]
        s.missing_cameras = sorted(set(missing) | set(absent))
        s.state = s.PARTIAL if s.missing_cameras else s.FINALIZED
        s.finalized = timezone.now()
        s.save(update_fields=["state", "missing_cameras", "finalized"])
        if missing:
            s.images.filter(file="").delete()
        _start_jobs(s)
    return s


def _start_jobs(s: CaptureSession):
    """Inside the finalizing transaction: the job a finalized session starts (dispatched after commit)."""
    if s.kind == "torso":
        job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=s.rig, session=s,
                                 calibration=s.rig.current_calibration)
        pipeline.dispatch(job)
        return
    # a test-field set is calibrated once all its poses are in. The rig's row is locked first: two last poses
    # finalized at once would each count the other's as missing (neither sees the other's uncommitted state)
    Rig.objects.select_for_update().filter(pk=s.rig_id).first()
    group = CaptureSession.objects.filter(rig=s.rig, kind="testfield", calibration_set=s.calibration_set,
                                          state__in=[s.FINALIZED, s.PARTIAL])
    expected = s.poses_expected or s.rig.poses_per_calibration
    if len(set(group.values_list("pose", flat=True))) < expected:
        return
    if Job.objects.filter(kind=Job.CALIBRATION, sessions__in=group).exists():
        return
    job = Job.objects.create(kind=Job.CALIBRATION, rig=s.rig, session=s)
    job.sessions.set(group)
    pipeline.dispatch(job)


# --- the rig's endpoints ------------------------------------------------------------------

@api.post("/sessions", auth=RigKeyAuth(), tags=["rig"])
def create_session(request, body: SessionIn):
    """Open a capture session from its manifest (``capture.json``). Retrying is harmless.

    Send an ``Idempotency-Key`` header to make retries explicit; without it
    the manifest's checksum identifies the session.
    """
    rig = request.rig
    check_json(body.manifest, "capture.json")
    serial = body.manifest.get("rig")
    if serial != rig.serial:
        raise ApiError(403, f"this key belongs to rig {rig.serial}; the manifest names rig {serial!r}")
    session, created = _create_session(rig, body, _idempotency_key(request, body.manifest))
    return _respond(request, _session_out(session), 201 if created else 200)


@api.put("/sessions/{session_id}/images/{camera}", auth=RigKeyAuth(), tags=["rig"])
def put_image(request, session_id: str, camera: str):
    """Upload one image as the raw request body. The server recomputes its sha256 and checks it decodes.

    Send it with a Content-Length (at most the server's MAX_IMAGE_BYTES).
    """
    body = _body(request, settings.MAX_IMAGE_BYTES, f"image of camera {camera!r}")
    s = get_object_or_404(_sessions_for(request), uid=_uuid(session_id))
    if s.state != s.OPEN:
        raise ApiError(409, f"session {s.uid} is finalized; it takes no more images")
    image = s.images.filter(camera=check_param(camera, "camera", 32)).first()
    if image is None:
        raise ApiError(400, f"unknown camera {camera!r}: not in session {s.uid}'s manifest")
    tmp, digest, size = _spool(body, settings.MAX_IMAGE_BYTES, f"image of camera {camera!r}")
    with tmp:
        if digest != image.sha256:
            raise ApiError(400, f"camera {camera!r}: sha256 mismatch (manifest {image.sha256}, received {digest}, "
                                f"{size} bytes); nothing was stored")
        if image.file:  # a repeated PUT of the same image
            return _respond(request, {"camera": camera, "sha256": digest, "size": size, "stored": "already"}, 200)
        _check_image(tmp, rig_from_dict(s.rig.description, f"rig {s.rig.serial}"), image, image.file_name)
        name = _store(image_path(image, image.file_name), tmp)
    try:
        outcome = _name_image(s, image, name, size)
    except (OperationalError, InterfaceError):
        # the connection was lost (a database restart, a network cut): once more on a new one. If the first
        # attempt committed after all, this one finds the row naming our file. If this fails too, the file
        # stays (a row may name it); the answer is 503 and the retry stores again (check_files finds the orphan).
        log.warning("session %s camera %s: database connection lost after storing %s; trying again", s.uid,
                    camera, name)
        connection.close()
        outcome = _name_image(s, image, name, size)
    if outcome != "now":  # another PUT of the same image won, or the session was finalized meanwhile
        _discard_unreferenced([name])
        if outcome == "finalized":
            raise ApiError(409, f"session {s.uid} was finalized meanwhile; the image was not stored")
        return _respond(request, {"camera": camera, "sha256": digest, "size": size, "stored": "already"}, 200)
    return _respond(request, {"camera": camera, "sha256": digest, "size": size, "stored": "now"}, 201)


def _name_image(session, image, name, size) -> str:
    """Point the image's row at the stored file ``name``: "now", or "already" (another upload's file is named),
    or "finalized" (the session closed meanwhile).

    The session's row is locked first (finalizing locks it too), so two uploads of one image take turns and
    the second sees the first's file. (A condition through a join, ``session__state=...``, is a subquery
    that PostgreSQL does not re-check after waiting for the first: both would "win", one file orphaned.)
    """
    with transaction.atomic():
        state = CaptureSession.objects.select_for_update().values_list("state", flat=True).get(pk=session.pk)
        if state != CaptureSession.OPEN:
            return "finalized"
        n = CaptureImage.objects.filter(pk=image.pk, file="").update(file=name, size=size, received=timezone.now())
    if n or CaptureImage.objects.filter(pk=image.pk, file=name).exists():  # ours, maybe by a lost first attempt
        return "now"
    return "already"


@api.post("/sessions/{session_id}/finalize", auth=RigKeyAuth(), tags=["rig"])
def finalize_session(request, session_id: str, partial: bool = False):
    """Close the session: complete, or (``?partial=true``) with the missing cameras named. Starts its job."""
    s = get_object_or_404(_sessions_for(request), uid=_uuid(session_id))
    s = _finalize(s, partial)
    return _respond(request, _session_out(s), 200)


def _store(name: str, fileobj) -> str:
    """Save to the storage, on disk before any row names it; a failing storage is a 503 (retry), not a 500."""
    try:
        stored = default_storage.save(name, File(fileobj))
        _to_disk(stored)
        return stored
    except Exception as exc:
        log.exception("storage failed saving %s", name)
        raise Unavailable(f"the file store failed ({type(exc).__name__})") from None


def _to_disk(name: str):
    """A file of a local storage, and its folder's entry, flushed to the disk: after a power cut a row committed
    since names a whole image (the storage writes the final name directly; a repeated upload answers "already"
    from the row). A storage without local paths (an object store) keeps its own promise."""
    try:
        path = default_storage.path(name)
    except NotImplementedError:
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    folder = os.open(os.path.dirname(path), os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def _stored(name: str) -> bool:
    try:
        return bool(name) and default_storage.exists(name)
    except Exception as exc:
        log.exception("storage failed checking %s", name)
        raise Unavailable(f"the file store failed ({type(exc).__name__})") from None


def _discard_unreferenced(names):
    """Delete what this request stored that no row points to. When the database cannot say (it is down), keep
    the files: an orphan costs disk space, a deleted image that a row points to costs a patient's scan."""
    if not names:
        return
    try:
        kept = set(CaptureImage.objects.filter(file__in=names).values_list("file", flat=True))
    except DatabaseError:
        log.warning("database unreachable: kept %d stored files of a failed upload", len(names))
        return
    for name in names:
        if name not in kept:
            try:
                default_storage.delete(name)
            except Exception:
                log.exception("could not delete %s (unreferenced, left behind)", name)


# what reading a corrupt, encrypted or oddly compressed zip member raises (a bad CRC, a truncated stream...)
ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, RuntimeError, NotImplementedError)


@contextlib.contextmanager
def _zip_member(zf, name: str):
    """A member opened for reading; its corruption is the bundle's fault (400 naming it), not a 500."""
    try:
        with zf.open(name) as member:
            yield member
    except ZIP_ERRORS as exc:
        raise ApiError(400, f"bundle.zip!{name}: cannot be read ({type(exc).__name__}: {exc})") from None


def _spool_member(zf, im, engine_rig):
    """A bundle's image spooled and checked against the manifest: (temporary file, size)."""
    declared = zf.getinfo(im.file).file_size
    if declared > settings.MAX_IMAGE_BYTES:
        raise ApiError(400, f"bundle.zip!{im.file}: camera {im.camera!r}: inflates to {declared} bytes, more than "
                            f"an image may have ({settings.MAX_IMAGE_BYTES})")
    with _zip_member(zf, im.file) as member:
        part, d, n = _spool(member, settings.MAX_IMAGE_BYTES, f"bundle.zip!{im.file}", status=400)
    try:
        if d != im.sha256:
            raise ApiError(400, f"bundle.zip!{im.file}: camera {im.camera!r}: sha256 mismatch "
                                f"(manifest {im.sha256}, file {d})")
        _check_image(part, engine_rig, CaptureImage(camera=im.camera, file_name=im.file), f"bundle.zip!{im.file}")
    except Exception:
        part.close()
        raise
    return part, n


def _complete_from_bundle(session: CaptureSession, zf, capture, engine_rig, manifest) -> CaptureSession:
    """A retried bundle of an existing session: whatever the session lacks (an image never stored, or lost
    from the store) is stored from the bundle, and an open session is finalized. Then it is whole."""
    if session.manifest_sha256 != _canonical_sha256(manifest):
        raise ApiError(409, f"session {session.uid} was opened with another capture.json under the same "
                            "Idempotency-Key")
    entries = {im.camera: im for im in capture.images}
    stored = []
    try:
        for image in session.images.all():
            if _stored(image.file.name):
                continue
            part, n = _spool_member(zf, entries[image.camera], engine_rig)
            with part:
                name = _store(image_path(image, image.file_name), part)
            stored.append(name)
            # only over what this row held before (nothing, or a lost file): a concurrent retry's file stays
            CaptureImage.objects.filter(pk=image.pk, file=image.file.name or "").update(
                file=name, size=n, received=timezone.now())
            log.warning("session %s: camera %s stored again from a retried bundle", session.uid, image.camera)
        if session.state == session.OPEN:
            session = _finalize(session, partial=False)
    finally:
        _discard_unreferenced(stored)
    session.refresh_from_db()
    return session


def _zip_entries(fh) -> Optional[int]:
    """How many members a zip's end-of-central-directory record declares (None when it cannot be found).

    Read before :class:`zipfile.ZipFile` parses the directory whole, which costs memory per member."""
    fh.seek(0, 2)
    end = fh.tell()
    fh.seek(max(0, end - (22 + 65535)))  # the record, after at most a 64 KiB comment
    tail = fh.read()
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or len(tail) < at + 22:
        return None
    (entries,) = struct.unpack("<H", tail[at + 10:at + 12])
    locator = at - 20  # zip64: the real count is in the zip64 record the locator points to
    if entries == 0xFFFF and locator >= 0 and tail[locator:locator + 4] == b"PK\x06\x07":
        (record,) = struct.unpack("<Q", tail[locator + 8:locator + 16])
        fh.seek(record)
        head = fh.read(40)
        if len(head) == 40 and head[:4] == b"PK\x06\x06":
            (entries,) = struct.unpack("<Q", head[32:40])
    return entries


def _read_manifest(zf) -> dict:
    """bundle.zip's capture.json, read in chunks up to MAX_MANIFEST_BYTES (its declared size may lie)."""
    limit = settings.MAX_MANIFEST_BYTES
    if zf.getinfo("capture.json").file_size > limit:
        raise ApiError(400, f"bundle.zip!capture.json: inflates to {zf.getinfo('capture.json').file_size} bytes, "
                            f"more than a manifest may have ({limit})")
    data = bytearray()
    with _zip_member(zf, "capture.json") as member:
        while chunk := member.read(CHUNK):
            data += chunk
            if len(data) > limit:
                raise ApiError(400, f"bundle.zip!capture.json is larger than {limit} bytes")
    try:
        return json.loads(bytes(data).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ApiError(400, f"bundle.zip!capture.json: not valid JSON ({type(exc).__name__}: {exc})") from None


@api.post("/bundles", auth=RigKeyAuth(), tags=["rig"])
def upload_bundle(request, visit: Optional[DbId] = None, calibration_set: Optional[CalibrationSet] = None,
                  poses: Optional[Poses] = None):
    """A whole capture bundle as one zip (raw body): checked whole, stored whole, finalized; or refused.

    Send it with a Content-Length (at most the server's MAX_BUNDLE_BYTES).
    Retrying is safe: a retry of a bundle already received answers 200 with
    its session, after storing again anything the session lacks.
    """
    rig = request.rig
    tmp, digest, size = _spool(_body(request, settings.MAX_BUNDLE_BYTES, "the bundle"), settings.MAX_BUNDLE_BYTES,
                               "the bundle")
    with tmp:
        if not zipfile.is_zipfile(tmp):
            raise ApiError(400, "the bundle is not a zip file")
        entries = _zip_entries(tmp)
        if entries is not None and entries > MAX_BUNDLE_MEMBERS:
            raise ApiError(400, f"bundle.zip holds {entries} members; a capture has at most {MAX_BUNDLE_MEMBERS}")
        tmp.seek(0)
        try:
            zf = zipfile.ZipFile(tmp)
        except ZIP_ERRORS as exc:
            raise ApiError(400, f"the bundle is not a readable zip file ({exc})") from None
        with zf:
            check_zip_members(zf, "bundle.zip")
            names = set(zf.namelist())
            if "capture.json" not in names:
                raise ApiError(400, "bundle.zip: no capture.json at the zip's root")
            manifest = _read_manifest(zf)
            if isinstance(manifest, dict):
                check_json(manifest, "bundle.zip!capture.json")
            if not isinstance(manifest, dict) or manifest.get("rig") != rig.serial:
                raise ApiError(403, f"this key belongs to rig {rig.serial}; the manifest names rig "
                                    f"{manifest.get('rig') if isinstance(manifest, dict) else None!r}")
            body = SessionIn(manifest=manifest, visit=visit, calibration_set=calibration_set, poses=poses)
            engine_rig = rig_from_dict(rig.description, f"rig {rig.serial}")
            capture = parse_capture_manifest(manifest, "bundle.zip!capture.json", engine_rig)
            check_capture(capture, manifest, "bundle.zip!capture.json")
            for im in capture.images:
                if im.file not in names:
                    raise ApiError(400, f"bundle.zip!{im.file}: camera {im.camera!r}: image file is missing")
            key = _idempotency_key(request, manifest)
            existing = CaptureSession.objects.filter(rig=rig, idempotency_key=key).first()
            if existing is not None:
                session = _complete_from_bundle(existing, zf, capture, engine_rig, manifest)
                return _respond(request, _session_out(session), 200)
            stored, checked = [], []
            try:
                for im in capture.images:
                    part, n = _spool_member(zf, im, engine_rig)
                    with part:
                        name = _store(f"captures/{rig.serial}/incoming-{digest[:16]}/{im.file}", part)
                    stored.append(name)
                    checked.append((im, name, n))
                # the session, its images and its job in one transaction: all of it is committed, or none
                with transaction.atomic():
                    session, created = _create_session(rig, body, key)
                    if created:
                        for im, name, n in checked:
                            CaptureImage.objects.filter(session=session, camera=im.camera).update(
                                file=name, size=n, received=timezone.now())
                        session = _finalize(session, partial=False)
            finally:
                _discard_unreferenced(stored)  # what no committed row points to (a failure, or a racing retry)
            if not created:  # the same retry raced us: the first one won; make sure it is whole
                session = _complete_from_bundle(session, zf, capture, engine_rig, manifest)
                return _respond(request, _session_out(session), 200)
    return _respond(request, _session_out(session), 201)


@api.get("/sessions/{session_id}", auth=[RigKeyAuth(), django_auth], tags=["rig"])
def session_status(request, session_id: str):
    s = get_object_or_404(_sessions_for(request).select_related("rig"), uid=_uuid(session_id))
    return _session_out(s)


@api.get("/jobs/{job_id}", auth=[RigKeyAuth(), django_auth], tags=["rig"])
def job_status(request, job_id: str):
    """Stage, percent and error of a job (poll this)."""
    return _job_out(get_object_or_404(_jobs_for(request), uid=_uuid(job_id)))


@api.get("/jobs/{job_id}/files/{name}", auth=[RigKeyAuth(), django_auth], tags=["rig"])
def job_file(request, job_id: str, name: str):
    """Download a result: ``torso.ply``, ``torso-mesh.ply``, ``report.json`` or ``calibration.json``."""
    job = get_object_or_404(_jobs_for(request), uid=_uuid(job_id))
    field = None
    if job.kind == Job.RECONSTRUCTION:
        rec = Reconstruction.objects.filter(job=job).first()
        if rec is not None:
            field = {"torso.ply": rec.torso, "torso-mesh.ply": rec.mesh, "report.json": rec.report_file}.get(name)
    elif name == "calibration.json" and hasattr(job, "calibration_result"):
        field = job.calibration_result.file
    if not field:
        raise ApiError(404, f"job {job.uid} has no file {name!r} (yet)")
    return FileResponse(default_storage.open(field.name, "rb"), as_attachment=True, filename=name)


def _uuid(value: str):
    import uuid

    try:
        return uuid.UUID(value)
    except ValueError:
        raise ApiError(404, f"{value!r} is not a session or job id") from None


# --- staff endpoints ----------------------------------------------------------------------

@api.post("/rigs", auth=django_auth, tags=["staff"])
def register_rig(request, body: RigIn):
    """Register a rig from its ``rig.json``; the answer holds its API key, shown this once."""
    clinic = member_clinic(request, body.clinic)
    check_json(body.rig, "rig.json")
    engine_rig = rig_from_dict(body.rig, "rig.json")
    check_rig(body.rig, engine_rig, "rig.json")
    if Rig.objects.filter(serial=engine_rig.serial).exists():
        raise ApiError(409, f"rig {engine_rig.serial} is already registered")
    with transaction.atomic():
        rig = Rig.objects.create(clinic=clinic, serial=engine_rig.serial, description=body.rig,
                                 recalibration_interval_days=body.recalibration_interval_days,
                                 poses_per_calibration=body.poses_per_calibration,
                                 needs_recalibration=True, recalibration_reason="never calibrated")
        sync_cameras(rig, engine_rig)
        _, key = RigKey.issue(rig)
    return _respond(request, {"serial": rig.serial, "key": key, "note": "store this key now: it is not shown again"}, 201)


def sync_cameras(rig: Rig, engine_rig) -> None:
    from .models import Camera

    for arm in engine_rig.arms:
        for pos, cam_id in enumerate(arm.cameras):
            spec = engine_rig.cameras[cam_id]
            Camera.objects.update_or_create(rig=rig, name=cam_id, defaults=dict(
                arm=arm.id, position=pos, width=spec.width, height=spec.height, pixel_size_mm=spec.pixel_size_mm,
                nominal_focal_mm=spec.nominal_focal_mm, model=spec.model or ""))


@api.post("/rigs/{serial}/keys", auth=django_auth, tags=["staff"])
def new_rig_key(request, serial: str):
    check_param(serial, "serial", 64)
    rig = get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)), serial=serial)
    member_clinic(request, rig.clinic_id)
    _, key = RigKey.issue(rig)
    return _respond(request, {"serial": rig.serial, "key": key, "note": "store this key now: it is not shown again"}, 201)


@api.delete("/rigs/{serial}/keys/{prefix}", auth=django_auth, tags=["staff"])
def revoke_rig_key(request, serial: str, prefix: str):
    check_param(serial, "serial", 64)
    check_param(prefix, "prefix", 16)
    rig = get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)), serial=serial)
    member_clinic(request, rig.clinic_id)
    n = rig.keys.filter(prefix=prefix, revoked__isnull=True).update(revoked=timezone.now())
    if not n:
        raise ApiError(404, f"rig {serial} has no live key starting {prefix!r}")
    return {"revoked": prefix}


@api.post("/testfields", auth=django_auth, tags=["staff"])
def register_testfield(request, body: TestFieldIn):
    from recon_engine.formats import read_testfield

    clinic = member_clinic(request, body.clinic)
    check_json(body.testfield, "testfield.json")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "testfield.json"
        path.write_text(json.dumps(body.testfield), encoding="utf-8")
        try:
            tf = read_testfield(path)
        except FormatError as exc:
            raise ApiError(400, str(exc).replace(str(path), "testfield.json")) from None
    check_length(tf.name, "testfield.json: name", 200)
    obj, created = TestField.objects.get_or_create(clinic=clinic, name=tf.name,
                                                   defaults={"description": body.testfield})
    if not created and obj.description != body.testfield:
        raise ApiError(409, f"test field {tf.name!r} is already registered with other coordinates")
    return _respond(request, {"name": obj.name}, 201 if created else 200)


@api.post("/patients", auth=django_auth, tags=["staff"])
def create_patient(request, body: PatientIn):
    clinic = member_clinic(request, body.clinic, roles=(Member.ADMINISTRATOR, Member.TECHNICIAN, Member.CLINICIAN))
    def exists():
        # with its id: a client whose first request's answer was lost goes on with the patient it made
        same = Patient.objects.filter(clinic=clinic, identifier=body.identifier).values_list("pk", flat=True).first()
        return ApiError(409, f"patient {body.identifier!r} already exists in {clinic.name} (id {same})")

    if Patient.objects.filter(clinic=clinic, identifier=body.identifier).exists():
        raise exists()
    try:
        with transaction.atomic():
            p = Patient.objects.create(clinic=clinic, identifier=body.identifier, name=body.name,
                                       date_of_birth=body.date_of_birth or None, sex=body.sex, notes=body.notes)
    except IntegrityError:  # made by another request since the check
        raise exists() from None
    return _respond(request, {"id": p.pk, "identifier": p.identifier}, 201)


IDEMPOTENCY_WAIT_S = 10.0  # how long a retry waits for the first request with its key to finish (then 503)
IDEMPOTENCY_SECONDS = 86400  # how long a visit's Idempotency-Key is remembered


@api.post("/patients/{patient_id}/visits", auth=django_auth, tags=["staff"])
def create_visit(request, body: VisitIn, patient_id: int = PathParam(..., ge=1, le=MAX_ID)):
    patient = get_object_or_404(Patient.objects.filter(clinic__in=clinics_of(request.user)), pk=patient_id)
    if body.date is not None and patient.date_of_birth and body.date < patient.date_of_birth:
        raise ApiError(400, f"date {body.date} is before the patient's date of birth ({patient.date_of_birth})")
    # a retried request (its answer lost) sends the same Idempotency-Key: it gets the visit the first made, not a
    # second one (clinic.once)
    key = check_param(request.headers.get("Idempotency-Key", ""), "Idempotency-Key header", 200)
    remembered = f"api-visit:{request.user.pk}:{patient.pk}:{hashlib.sha256(key.encode()).hexdigest()}"
    if key and not once.claim(remembered, IDEMPOTENCY_SECONDS):  # an earlier request's: its visit, once made
        made = once.first_outcome(remembered, IDEMPOTENCY_WAIT_S)
        if made == once.PENDING:
            raise Unavailable("the first request with this Idempotency-Key is still making its visit (retry with "
                              "the same key)")
        earlier = Visit.objects.filter(pk=made, patient=patient).first() if made else None
        if earlier is not None:
            return _respond(request, {"id": earlier.pk, "date": str(earlier.date)}, 200)
        # the first failed, the cache forgot it, or its visit was erased: this request makes one
        once.settle(remembered, once.PENDING, IDEMPOTENCY_SECONDS)
    try:
        v = Visit.objects.create(patient=patient, date=body.date or timezone.localdate(), clinician=request.user,
                                 reason=body.reason, notes=body.notes)
    except BaseException:
        if key:
            once.release(remembered)
        raise
    if key:
        once.settle(remembered, v.pk, IDEMPOTENCY_SECONDS)
    return _respond(request, {"id": v.pk, "date": str(v.date)}, 201)


RERUN_LANDMARKS = (Member.ADMINISTRATOR, Member.TECHNICIAN, Member.CLINICIAN)


@api.post("/jobs/{job_id}/rerun", auth=django_auth, tags=["staff"])
def rerun_job(request, job_id: str):
    """Run a failed job again (its capture was kept), e.g. after the rig was calibrated.

    A job stuck running whose worker died (every lease lapsed) is re-run too;
    409 while a worker holds it. A queued job is sent to the broker again. A
    reconstruction that succeeded is not re-run (409): its torso, the
    landmarks a clinician corrected on it and its comparisons would be deleted
    before a new torso exists. A landmark correction's job may be re-run by
    its clinicians too.
    """
    job = get_object_or_404(_jobs_for(request), uid=_uuid(job_id))
    # a landmark correction's job is the clinician's too (a server fault left the correction kept, not applied)
    member_clinic(request, job.clinic_id, RERUN_LANDMARKS if job.kind == Job.LANDMARKS else
                  (Member.ADMINISTRATOR, Member.TECHNICIAN))
    try:
        job = pipeline.rerun(job)
    except pipeline.JobError as exc:
        raise ApiError(409, str(exc)) from None
    return _job_out(job)

