"""The work behind the Celery tasks: calibration, arms, registration, comparison.

Every step claims its unit of work with a conditional UPDATE on the job's
(or the arm's) row, so a task delivered twice does the work once, and records
its durable state there: the broker only carries ids. Engine stages are
called through ``recon_engine``'s public functions.

The rows are also the outbox: a job committed as queued is the record of work
to do, whether or not the broker took the message. A claim holds a lease that
the running step renews (a heartbeat); ``redispatch_stalled`` (Celery beat, or
``manage.py dispatch_queued``) sends again whatever was not sent, was lost with
the broker, or whose worker died (its lease ran out).
"""

import json
import logging
import secrets
import shutil
import tempfile
import threading
from datetime import timedelta
from pathlib import Path

from django.conf import settings
from django.core.files import File
from django.core.files.base import ContentFile
from django.core.files.storage import default_storage
from django.db import IntegrityError, InterfaceError, OperationalError, connection, transaction
from django.db.models import Exists, F, OuterRef, Q
from django.utils import timezone

from recon_engine.formats import FormatError, read_calibration, read_capture, rig_from_dict

from .models import ArmTask, Calibration, CaptureSession, Job, Reconstruction, StabilityCheck

log = logging.getLogger(__name__)

# faults worth a retry: the database or the broker briefly unreachable (never the engine's errors)
TRANSIENT = (OperationalError, InterfaceError, ConnectionError, TimeoutError)

# where each stage's progress starts (percent)
ARMS_START, REGISTRATION_START, ANALYSIS_START, COMPARISON_START = 5, 70, 85, 92
COMPARISON_RUN_START = 10  # a comparison job: one step, no finer progress from the analysis


class JobError(Exception):
    """A problem the technician can act on (bad capture, missing calibration, …)."""


def _now():
    return timezone.now()


def _lease():
    return _now() + timedelta(seconds=settings.JOB_LEASE_SECONDS)


def _lapsed():
    """A running claim whose lease ran out: its worker died (or stalled) and another may take it over."""
    return Q(state=Job.RUNNING, lease_until__lt=_now())


def set_progress(job_id, stage=None, percent=None):
    fields = {}
    if stage is not None:
        fields["stage"] = stage
    if percent is not None:
        fields["percent"] = max(0, min(100, int(percent)))
    Job.objects.filter(pk=job_id, state=Job.RUNNING).update(**fields)
    # progress is a sign of life: it renews the lease of the step holding the job (none while the arms run)
    Job.objects.filter(pk=job_id, state=Job.RUNNING, lease_until__isnull=False).update(lease_until=_lease())


def fail(job_id, error: str, claimed=None):
    """The job failed; with ``claimed``, only if that claim still holds it (not after a takeover or re-run)."""
    log.warning("job %s failed: %s", job_id, error)
    rows = Job.objects.filter(pk=job_id) if claimed is None else Job.objects.filter(pk=job_id, claimed=claimed)
    rows.update(state=Job.FAILED, error=error[:5000], finished=_now(), lease_until=None)


class heartbeat:
    """While a step works, renew its claim's lease from a thread (the engine's calls give no progress).

    ``rows`` is the claimed row's queryset, filtered on its claim, so a step
    that lost its claim (taken over after its lease lapsed) stops renewing it.
    """

    def __init__(self, rows):
        self.rows, self.stop = rows, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="lease-heartbeat")

    def _run(self):
        interval = max(settings.JOB_LEASE_SECONDS / 4, 0.5)
        try:
            while not self.stop.wait(interval):
                try:
                    if not self.rows.filter(state=Job.RUNNING).update(lease_until=_lease()):
                        return
                except TRANSIENT:
                    log.warning("could not renew a lease (database unreachable); trying again")
        finally:
            connection.close()  # this thread's own connection

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


def _engine_error(exc: Exception) -> str:
    """The job's error in words for the pages and the API. An unexpected fault's traceback goes to the server's
    log under an id the job's error names: the pages and the rig's API never show the server's code."""
    if isinstance(exc, (FormatError, ValueError, JobError)):
        return str(exc)
    error_id = secrets.token_hex(4)
    log.error("internal fault %s in a job", error_id, exc_info=exc)
    return (f"{type(exc).__name__}: {str(exc)[:300]} (an internal fault; its traceback is in the server's log as "
            f"{error_id})")


# --- dispatch ------------------------------------------------------------------

def send(task, *args) -> bool:
    """Hand a step to the broker. Failing to is logged, never raised: the row keeps the work, and
    ``redispatch_stalled`` sends it again. Without a broker (eager), the step runs here, as it always did."""
    if settings.CELERY_TASK_ALWAYS_EAGER:
        task.delay(*args)
        return True
    try:
        task.delay(*args)
        return True
    except Exception:
        log.exception("could not send %s%r to the broker; the sweeper will send it again", task.name, tuple(args))
        return False


def _entry_task(job: Job):
    from . import tasks

    return {Job.CALIBRATION: tasks.run_calibration, Job.COMPARISON: tasks.run_comparison,
            Job.LANDMARKS: tasks.run_landmark_analysis}.get(job.kind, tasks.start_reconstruction)


def dispatch(job: Job):
    """Start ``job`` once the surrounding transaction commits (never before its row is visible).

    The committed queued row is what counts: if the broker is down now, the
    request still succeeds and the sweeper sends the job later.
    """
    task = _entry_task(job)
    transaction.on_commit(lambda: send(task, job.pk))


def _abandoned():
    """Running jobs that nothing holds: neither the job's lease nor any arm's is live."""
    now = _now()
    live_arm = ArmTask.objects.filter(job=OuterRef("pk"), state=Job.RUNNING, lease_until__gte=now)
    return Q(state=Job.RUNNING) & (Q(lease_until=None) | Q(lease_until__lt=now)) & ~Exists(live_arm)


def rerun(job: Job) -> Job:
    """Put a failed (or finished) job back in the queue; its capture was kept.

    A job still running can be re-run once no worker holds it (every lease
    lapsed): its worker died. A queued job is sent again (it may never have
    reached the broker; a second delivery is refused by its claim).
    """
    if Job.objects.filter(pk=job.pk, state=Job.QUEUED).update(dispatched=_now()):
        job.refresh_from_db()
        send(_entry_task(job), job.pk)
        return job
    with transaction.atomic():
        # a calibration that succeeded is history (stability checks refer to it): calibrate anew instead. A
        # reconstruction that succeeded is the patient's torso: re-running it would delete it (and its landmark
        # corrections and comparisons) before a new one exists, and a run that then failed would leave none
        rerunnable = [Job.FAILED] if job.kind in (Job.CALIBRATION, Job.RECONSTRUCTION) else [Job.FAILED,
                                                                                             Job.SUCCEEDED]
        n = Job.objects.filter(Q(pk=job.pk) & (Q(state__in=rerunnable) | _abandoned())).update(
            state=Job.QUEUED, stage="", percent=0, error="", finished=None, claimed=None, lease_until=None,
            dispatched=_now(), takeovers=0)
        if not n:
            job.refresh_from_db()
            if job.state == Job.RUNNING:
                raise JobError(f"job {job.uid} is running and its worker is alive (its claim is renewed, and lapses "
                               f"{settings.JOB_LEASE_SECONDS} s after the worker stops); re-run it only after that")
            raise JobError(f"job {job.uid} is {job.state}; only a "
                           f"{' or '.join(rerunnable)} {job.kind} job (or a running one whose worker died) "
                           "can be re-run")
        job.arms.all().delete()
        if job.kind == Job.RECONSTRUCTION:
            Reconstruction.objects.filter(job=job).delete()
            job.calibration = job.rig.current_calibration
            job.save(update_fields=["calibration"])
        job.refresh_from_db()
        dispatch(job)
    return job


# --- files -----------------------------------------------------------------------

def materialize(session: CaptureSession, dest: Path, cameras=None) -> Path:
    """The session's received images as a capture bundle folder under ``dest`` (for the engine)."""
    dest.mkdir(parents=True, exist_ok=True)
    images = [im for im in session.images.all() if im.file and (cameras is None or im.camera in cameras)]
    manifest = dict(session.manifest)
    keep = {im.camera for im in images}
    manifest["images"] = [e for e in session.manifest["images"] if e["camera"] in keep]
    (dest / "capture.json").write_text(json.dumps(manifest), encoding="utf-8")
    for im in images:
        target = dest / im.file_name
        target.parent.mkdir(parents=True, exist_ok=True)
        with default_storage.open(im.file.name, "rb") as src, open(target, "wb") as out:
            shutil.copyfileobj(src, out, 1 << 20)
    return dest


def _calibration_on_disk(calibration: Calibration, dest: Path):
    path = dest / "calibration.json"
    with default_storage.open(calibration.file.name, "rb") as src, open(path, "wb") as out:
        shutil.copyfileobj(src, out)
    return read_calibration(path)


def _workdir():
    root = Path(settings.WORK_DIR)
    root.mkdir(parents=True, exist_ok=True)
    return tempfile.TemporaryDirectory(dir=root)


# --- calibration --------------------------------------------------------------------

def run_calibration(job_id: int) -> str:
    from recon_engine.calibration import calibrate
    from recon_engine.formats import read_testfield, write_calibration
    from recon_engine.stability import compare_calibrations

    claim = _now()
    n = Job.objects.filter(Q(pk=job_id, kind=Job.CALIBRATION) & (Q(state=Job.QUEUED) | _lapsed())).update(
        state=Job.RUNNING, stage="measuring targets", percent=5, claimed=claim, lease_until=_lease(),
        started=claim, attempt=F("attempt") + 1)
    if not n:
        return "not claimed"
    job = Job.objects.select_related("rig").get(pk=job_id)
    rig = rig_from_dict(job.rig.description, f"rig {job.rig.serial}")
    sessions = list(job.sessions.select_related("testfield").order_by("pose", "id"))
    try:
        with _workdir() as tmp, heartbeat(Job.objects.filter(pk=job_id, claimed=claim)):
            tmp = Path(tmp)
            if not sessions:
                raise JobError("the calibration job has no test-field sessions")
            testfield = sessions[0].testfield
            tf_path = tmp / "testfield.json"
            tf_path.write_text(json.dumps(testfield.description), encoding="utf-8")
            tf = read_testfield(tf_path)
            captures = [read_capture(materialize(s, tmp / f"pose{s.pose}-{s.pk}"), rig) for s in sessions]
            set_progress(job_id, "bundle adjustment", 20)
            calib, report = calibrate(captures, rig, tf)
            set_progress(job_id, "stability checks", 85)
            out = tmp / "calibration.json"
            write_calibration(out, calib)
            figures = report.to_dict()
            with open(out, "rb") as fh:
                content = fh.read()
        sigmas = calib.extra.get("sigmas", {})
        with transaction.atomic():
            record = Calibration.objects.create(rig=job.rig, job=job, figures=figures, sigmas=sigmas,
                                                calibrated_at=_now())
            record.file.save(f"{job.rig.serial}-{job.uid}.json", ContentFile(content), save=True)
            previous = (Calibration.objects.filter(rig=job.rig, status=Calibration.SUCCEEDED)
                        .exclude(pk=record.pk).order_by("-calibrated_at", "-id").first())
            unstable = []
            if previous is not None:
                with _workdir() as tmp2:
                    before = _calibration_on_disk(previous, Path(tmp2))
                result = compare_calibrations(before, calib)
                cameras = {c.name: c for c in job.rig.cameras.all()}
                for cam_id, m in result["cameras"].items():
                    if cam_id not in cameras:
                        continue
                    thr = m["threshold_px"]
                    StabilityCheck.objects.get_or_create(
                        camera=cameras[cam_id], calibration=record, reference=previous,
                        defaults=dict(zrot_px=m["zrot_px"], rot_px=m["rot_px"], spr_px=m["spr_px"],
                                      arm_px=m.get("arm_px"), threshold_px=max(thr.values()),
                                      thresholds=thr, exceeds=m["exceeds"], stable=m["stable"]))
                    if not m["stable"]:
                        unstable.append(cam_id)
            rig = job.rig
            if unstable:
                rig.needs_recalibration = True
                rig.recalibration_reason = f"cameras failed the stability check: {', '.join(unstable)}"
            else:
                rig.needs_recalibration = False
                rig.recalibration_reason = ""
            rig.save(update_fields=["needs_recalibration", "recalibration_reason"])
            if not Job.objects.filter(pk=job_id, state=Job.RUNNING, claimed=claim).update(
                    state=Job.SUCCEEDED, stage="done", percent=100, finished=_now(), lease_until=None):
                # another worker took the job over (this one had stalled past its lease): its result counts
                raise _ClaimLost()
        return "succeeded"
    except _ClaimLost:
        return "claim lost"
    except TRANSIENT:
        Job.objects.filter(pk=job_id, claimed=claim).update(state=Job.QUEUED, claimed=None, lease_until=None)
        raise
    except Exception as exc:  # the engine's error becomes the job's, for the technician
        fail(job_id, f"calibration: {_engine_error(exc)}", claimed=claim)
        return "failed"


class _ClaimLost(Exception):
    """Rolls back a step's results: its claim was taken over meanwhile."""


# --- reconstruction -------------------------------------------------------------------

def start_reconstruction(job_id: int) -> list:
    """Claim the job and create its arm rows; the arms to dispatch (empty when not claimed)."""
    claim = _now()
    # a start that died before its arms existed (lease lapsed, stage still "arms") is started again
    n = Job.objects.filter(Q(pk=job_id, kind=Job.RECONSTRUCTION)
                           & (Q(state=Job.QUEUED) | (_lapsed() & Q(stage="arms")))).update(
        state=Job.RUNNING, stage="arms", percent=ARMS_START, claimed=claim, lease_until=_lease(), started=claim,
        attempt=F("attempt") + 1)
    if not n:
        return []
    job = Job.objects.select_related("rig", "session", "calibration").get(pk=job_id)
    if job.calibration is None:
        fail(job_id, f"rig {job.rig.serial} has no calibration yet: upload its test-field captures, "
                     "then re-run this job", claimed=claim)
        return []
    rig = rig_from_dict(job.rig.description, f"rig {job.rig.serial}")
    arms = [a.id for a in rig.arms]
    with transaction.atomic():
        job.arms.exclude(state=Job.SUCCEEDED).update(state=Job.QUEUED, claimed=None, lease_until=None, error="",
                                                     dispatched=_now())
        for arm in arms:
            ArmTask.objects.get_or_create(job=job, arm=arm)
        # from here the arms hold the work (each its own lease); the job's row only joins them
        Job.objects.filter(pk=job_id, claimed=claim).update(lease_until=None)
    return [a.arm for a in job.arms.exclude(state=Job.SUCCEEDED)]


def reconstruct_arm(job_id: int, arm: str) -> str:
    """One arm of a reconstruction job; the last arm to finish hands over to the registration."""
    from recon_engine.reconstruction import reconstruct_arm as engine_reconstruct_arm
    from recon_engine.results import arm_surface_bytes

    claim = _now()
    n = ArmTask.objects.filter(Q(job_id=job_id, arm=arm, job__state=Job.RUNNING)
                               & (Q(state=Job.QUEUED) | _lapsed())
                               ).update(state=Job.RUNNING, claimed=claim, lease_until=_lease())
    if not n:
        return "not claimed"
    task = ArmTask.objects.select_related("job__rig", "job__session", "job__calibration").get(job_id=job_id, arm=arm)
    job = task.job
    mine = ArmTask.objects.filter(pk=task.pk, state=Job.RUNNING, claimed=claim)
    try:
        rig = rig_from_dict(job.rig.description, f"rig {job.rig.serial}")
        cameras = next(a.cameras for a in rig.arms if a.id == arm)
        with _workdir() as tmp, heartbeat(mine):
            tmp = Path(tmp)
            calibration = _calibration_on_disk(job.calibration, tmp)
            capture = read_capture(materialize(job.session, tmp / "capture", cameras), rig)
            surface, report = engine_reconstruct_arm(capture, rig, calibration, arm)
        task.surface.save(f"arm-{arm}.npz", ContentFile(arm_surface_bytes(surface)), save=False)
        if not mine.update(surface=task.surface.name, report=report, state=Job.SUCCEEDED, lease_until=None):
            _discard_unnamed_surface(task.surface.name)
            return "claim lost"  # taken over after this worker stalled past its lease: the other one finishes
    except TRANSIENT:
        # stored, but the update naming it was lost with the connection
        _discard_unnamed_surface(task.surface.name, reconnect=True)
        mine.update(state=Job.QUEUED, claimed=None, lease_until=None)
        raise
    except Exception as exc:
        if not mine.update(state=Job.FAILED, error=_engine_error(exc), lease_until=None):
            return "claim lost"
    return "arms done" if arms_finished(job_id) else "arm done"


def _discard_unnamed_surface(name: str, reconnect=False):
    """Delete an arm surface this step stored if no row names it, checked on a new connection (the old one may
    be the one lost). When the database cannot say, the file stays: ``manage.py check_files`` reports it."""
    if not name:
        return
    if reconnect and not connection.in_atomic_block:
        connection.close()
    try:
        if ArmTask.objects.filter(surface=name).exists():
            return
    except TRANSIENT:
        log.warning("arm surface %s kept: the database cannot say whether a row names it", name)
        return
    default_storage.delete(name)


def arms_finished(job_id) -> bool:
    """Progress after an arm; once every arm is done, the job is handed over to the registration (once)."""
    arms = ArmTask.objects.filter(job_id=job_id)
    done, total = arms.filter(state__in=[Job.SUCCEEDED, Job.FAILED]).count(), arms.count()
    set_progress(job_id, percent=ARMS_START + (REGISTRATION_START - ARMS_START) * done / max(total, 1))
    return bool(total and done == total and Job.objects.filter(
        pk=job_id, state=Job.RUNNING, stage="arms", lease_until=None).update(
            stage="registration queued", percent=REGISTRATION_START, dispatched=_now()))


REGISTRATION_STAGES = ["registration", "indices and pictures", "comparison"]


def register(job_id: int) -> str:
    """Registration of the arm surfaces, the torso files, then comparison with earlier visits."""
    claim = _now()
    # handed over by the last arm, or a registration whose worker died (its lease lapsed): done again
    if not Job.objects.filter(Q(pk=job_id, state=Job.RUNNING)
                              & (Q(stage="registration queued") | (_lapsed() & Q(stage__in=REGISTRATION_STAGES)))
                              ).update(stage="registration", claimed=claim, lease_until=_lease()):
        return "not claimed"
    job = Job.objects.select_related("rig", "session", "calibration").get(pk=job_id)
    try:
        with heartbeat(Job.objects.filter(pk=job_id, claimed=claim)):
            return _register(job, claim)
    except TRANSIENT:
        Job.objects.filter(pk=job_id, claimed=claim).update(stage="registration queued", lease_until=None,
                                                            dispatched=_now())
        raise
    except Exception as exc:
        fail(job_id, f"registration: {_engine_error(exc)}", claimed=claim)
        return "failed"


def _stored_under(folder: str) -> list:
    from .filecheck import stored_names

    return list(stored_names(default_storage, folder))


def _comparison_files(pair: str) -> list:
    """Stored files of the comparisons whose "<earlier pk>-<later pk>" matches the regular expression ``pair``:
    compare_reconstructions stores "comparisons/<pair>-deformation*.ply" and "comparisons/<pair>/*.png"."""
    import re

    try:
        dirs, files = default_storage.listdir("comparisons")
    except FileNotFoundError:
        return []
    found = [f"comparisons/{n}" for n in files if re.fullmatch(rf"({pair})-deformation[^/]*\.ply", n)]
    for d in dirs:
        if re.fullmatch(pair, d):
            found += _stored_under(f"comparisons/{d}")
    return found


def _forget_half_made(job: Job):
    """What a registration that died half-way left, removed so that the next attempt stores one set: its torso
    rows, their comparisons, and every file it stored, whether a row named it yet or not (the job's result
    folder less the arms' surfaces; the comparison files of the removed torsos). Only the holder of the
    registration's claim calls this, so nothing else is writing these files."""
    keep = set(ArmTask.objects.filter(job=job).exclude(surface="").values_list("surface", flat=True))
    files = [n for n in _stored_under(f"results/{job.uid}") if n not in keep]
    old = list(Reconstruction.objects.filter(job=job))
    if old:
        files += _comparison_files(rf"\d+-({'|'.join(str(rec.pk) for rec in old)})")
    for rec in old:
        forget_comparisons_of(rec)
    Reconstruction.objects.filter(job=job).delete()
    if files:
        log.warning("job %s: removing %d files a registration that died half-way left", job.uid, len(files))
    transaction.on_commit(lambda: [default_storage.delete(f) for f in files])


def _register(job: Job, claim) -> str:
    from recon_engine.reconstruction import register_arms
    from recon_engine.results import read_arm_surface, write_torso

    _forget_half_made(job)
    rig = rig_from_dict(job.rig.description, f"rig {job.rig.serial}")
    surfaces, reports, failed = {}, {}, {}
    for task in job.arms.all():
        if task.state == Job.SUCCEEDED:
            with default_storage.open(task.surface.name, "rb") as fh:
                surfaces[task.arm] = read_arm_surface(fh)
            reports[task.arm] = task.report
        else:
            failed[task.arm] = task.error or "not reconstructed"
    with _workdir() as tmp:
        tmp = Path(tmp)
        calibration = _calibration_on_disk(job.calibration, tmp)
        result = register_arms(surfaces, reports, failed, rig, calibration)
        paths = write_torso(tmp / "out", result)
        rec = Reconstruction(job=job, session=job.session, report=result["report"],
                             status=result["report"]["status"], points=result["report"]["points"])
        for field, path in zip(("torso", "mesh", "report_file"), paths):
            with open(path, "rb") as fh:
                getattr(rec, field).save(path.name, File(fh), save=False)
        with transaction.atomic():
            # still ours? A worker slowed past its lease (a loaded machine) may find the registration handed to a
            # redelivery meanwhile: that one forgot what was half-made when it took over and stores the torso
            # itself, so this one stores none (two torsos of one job: the second's insert failed the job)
            if not Job.objects.select_for_update().filter(pk=job.pk, state=Job.RUNNING, claimed=claim).exists():
                stored = [getattr(rec, f).name for f in ("torso", "mesh", "report_file")]
                transaction.on_commit(lambda: [default_storage.delete(n) for n in stored if n])
                log.warning("job %s: registration taken over by a redelivery; this worker's torso discarded", job.uid)
                return "claim lost"
            rec.save()
    if rec.status == "failed":
        # the files stay for inspection, but the torso is not presented as good
        fail(job.pk, "registration: " + "; ".join(result["report"]["problems"]), claimed=claim)
        return "failed"
    set_progress(job.pk, "indices and pictures", ANALYSIS_START)
    from .analysis_step import analyse_reconstruction

    analyse_reconstruction(rec)
    set_progress(job.pk, "comparison", COMPARISON_START)
    compare_with_earlier(rec)
    if not Job.objects.filter(pk=job.pk, state=Job.RUNNING, claimed=claim).update(
            state=Job.SUCCEEDED, stage="done", percent=100, finished=_now(), lease_until=None):
        return "claim lost"
    return "succeeded"


def earlier_reconstructions(rec: Reconstruction):
    """What ``rec`` is compared with: the latest good torso of each earlier visit of the patient
    (a change), and every earlier good torso of its own visit (a repeat pair)."""
    visit = rec.session.visit
    if visit is None:
        return []
    good = (Reconstruction.objects.filter(session__visit__patient=visit.patient, status__in=["ok", "partial"],
                                          job__state=Job.SUCCEEDED)
            .exclude(pk=rec.pk).select_related("session__visit").order_by("-created"))
    earlier = good.filter(Q(session__visit__date__lt=visit.date)
                          | Q(session__visit__date=visit.date, session__visit_id__lt=visit.id))
    latest = {}
    for r in earlier:
        latest.setdefault(r.session.visit_id, r)
    repeats = list(good.filter(session__visit=visit, created__lt=rec.created))
    return list(latest.values()) + repeats


def compare_with_earlier(rec: Reconstruction) -> list:
    """The later torso against every earlier visit's (the analysis step). A pair whose earlier torso's landmarks
    were corrected while it was compared is left to that correction's job, which compares it again."""
    from .analysis_step import StaleComparison, compare_reconstructions

    out = []
    for earlier in earlier_reconstructions(rec):
        try:
            out.append(compare_reconstructions(earlier, rec))
        except StaleComparison as exc:
            log.info("torso %s: %s", rec.pk, exc)
    return out


# --- a comparison asked for on its page ------------------------------------------------

def request_comparison(earlier: Reconstruction, later: Reconstruction) -> Job:
    """The job comparing ``later`` with ``earlier``: the pair's existing one, or a new one, sent.

    Two requests at once make one job: the pair is unique among comparison
    jobs, and the request that loses the race takes the winner's job (only
    the winner sends it). Without a broker the job runs here, before this
    returns. Called outside a transaction (the pages run in autocommit), so
    the row is committed before a worker looks for it; if the broker is down,
    the sweeper sends it later.
    """
    job = comparison_job_of(earlier, later)
    if job is not None:
        return job
    try:
        with transaction.atomic():
            job = _comparison_job_row(earlier, later)
    except IntegrityError:
        return Job.objects.get(kind=Job.COMPARISON, earlier=earlier, later=later)
    send(_entry_task(job), job.pk)
    job.refresh_from_db()
    return job


def _comparison_job_row(earlier: Reconstruction, later: Reconstruction) -> Job:
    """A queued comparison job's row (not sent): the session is the later torso's, so the job is its patient's."""
    return Job.objects.create(kind=Job.COMPARISON, rig_id=later.session.rig_id, session_id=later.session_id,
                              earlier=earlier, later=later, stage="waiting for a worker")


def comparison_job_of(earlier: Reconstruction, later: Reconstruction):
    return Job.objects.filter(kind=Job.COMPARISON, earlier=earlier, later=later).first()


def run_comparison(job_id: int) -> str:
    """Register the later torso to the earlier one: the report, deformation map and its picture (once per pair)."""
    from .analysis_step import StaleComparison, compare_reconstructions

    claim = _now()
    if not Job.objects.filter(Q(pk=job_id, kind=Job.COMPARISON) & (Q(state=Job.QUEUED) | _lapsed())).update(
            state=Job.RUNNING, stage="lining up the two torsos", percent=COMPARISON_RUN_START, claimed=claim,
            lease_until=_lease(), started=claim, attempt=F("attempt") + 1):
        return "not claimed"
    job = Job.objects.select_related("earlier__session__rig__clinic", "later__session__rig__clinic").get(pk=job_id)
    if job.attempt > 1:
        _forget_half_made_comparison(job.earlier_id, job.later_id)
    try:
        with heartbeat(Job.objects.filter(pk=job_id, claimed=claim)):
            # a pair the registration compared meanwhile is not computed again (nor stored twice)
            compare_reconstructions(job.earlier, job.later)
    except StaleComparison as exc:  # the correction's job has queued the pair again (this job row is gone)
        log.info("comparison job %s: %s", job_id, exc)
        fail(job_id, f"comparison: {exc}", claimed=claim)
        return "stale"
    except TRANSIENT:
        Job.objects.filter(pk=job_id, claimed=claim).update(state=Job.QUEUED, claimed=None, lease_until=None)
        raise
    except Exception as exc:
        fail(job_id, f"comparison: {_engine_error(exc)}", claimed=claim)
        return "failed"
    if not Job.objects.filter(pk=job_id, state=Job.RUNNING, claimed=claim).update(
            state=Job.SUCCEEDED, stage="done", percent=100, finished=_now(), lease_until=None):
        return "claim lost"
    return "succeeded"


# --- a torso's landmarks corrected by a clinician ------------------------------------

LANDMARKS_RUN_START = 10  # one step (indices and pictures, then the comparisons are queued)


def queue_landmark_analysis(rec: Reconstruction) -> Job:
    """The row of the job that will compute ``rec``'s indices and pictures again from its corrected landmarks,
    made in the caller's transaction: the one that stores the landmarks, so that the two commit together and a
    correction never stands without its job. Hand it to :func:`send_now` once committed (a queued job that
    never reaches the broker is sent by the sweeper). A job of the same torso still waiting is reused (two
    corrections in a row: the second's landmarks are what it reads)."""
    job = Job.objects.filter(kind=Job.LANDMARKS, later=rec, state=Job.QUEUED).first()
    if job is None:
        job = Job.objects.create(kind=Job.LANDMARKS, rig_id=rec.session.rig_id, session_id=rec.session_id,
                                 later=rec, stage="waiting for a worker")
    return job


def send_now(job: Job) -> Job:
    """A committed queued ``job`` handed to the broker (without one, run here before this returns); the job as
    it stands after that."""
    send(_entry_task(job), job.pk)
    job.refresh_from_db()
    return job


def landmark_job_of(rec: Reconstruction):
    """The latest landmark job of ``rec`` (what its visit page shows while it runs, or why it failed)."""
    return Job.objects.filter(kind=Job.LANDMARKS, later=rec).order_by("-created").first()


def run_landmark_analysis(job_id: int) -> str:
    """Indices and pictures of a torso from its corrected landmarks; then the comparisons resting on it are
    removed and queued again. If the indices cannot be computed from these landmarks, the correction is undone
    (the landmarks before it come back) and the job fails saying so."""
    from .analysis_step import analyse_reconstruction

    claim = _now()
    if not Job.objects.filter(Q(pk=job_id, kind=Job.LANDMARKS) & (Q(state=Job.QUEUED) | _lapsed())).update(
            state=Job.RUNNING, stage="indices and pictures", percent=LANDMARKS_RUN_START, claimed=claim,
            lease_until=_lease(), started=claim, attempt=F("attempt") + 1):
        return "not claimed"
    job = Job.objects.select_related("later__session").get(pk=job_id)
    rec = job.later
    read = json.dumps([rec.landmarks, rec.landmark_history], sort_keys=True)  # the correction this job applies
    try:
        with heartbeat(Job.objects.filter(pk=job_id, claimed=claim)), transaction.atomic():
            analyse_reconstruction(rec)
            # the comparisons resting on the torso go, and their new jobs' rows come, in one commit: a worker
            # that dies after it cannot lose them (the sweeper sends a queued row)
            again = [_comparison_job_row(earlier, later) for earlier, later in forget_comparisons_of(rec)]
    except TRANSIENT:
        Job.objects.filter(pk=job_id, claimed=claim).update(state=Job.QUEUED, claimed=None, lease_until=None)
        raise
    except (ValueError, FormatError) as exc:
        # the analysis refused these landmarks: the correction is undone, unless another one came meanwhile
        # (its own job reads it)
        log.exception("torso %s: indices from the corrected landmarks %s failed", rec.pk, rec.landmarks)
        with transaction.atomic():
            now = Reconstruction.objects.select_for_update().get(pk=rec.pk)
            history = list(now.landmark_history or [])
            undone = bool(history) and json.dumps([now.landmarks, now.landmark_history], sort_keys=True) == read
            if undone:
                last = history.pop()
                Reconstruction.objects.filter(pk=rec.pk).update(landmarks=last.get("landmarks"),
                                                                landmark_history=history)
        fail(job_id, "the indices could not be computed from the corrected landmarks, so "
                     + ("the correction was undone" if undone else "they were not used")
                     + f": {_engine_error(exc)}", claimed=claim)
        return "failed"
    except Exception as exc:
        # a fault of the server (a full disk, a time limit), not of the landmarks: the correction is kept, and
        # the job can be run again once the fault is mended
        fail(job_id, "the indices could not be computed again (a fault of the server, not of the landmarks; the "
                     f"correction is kept: run this job again): {_engine_error(exc)}", claimed=claim)
        return "failed"
    set_progress(job_id, "comparisons queued", 90)
    for comparison in again:
        send_now(comparison)
    if not Job.objects.filter(pk=job_id, state=Job.RUNNING, claimed=claim).update(
            state=Job.SUCCEEDED, stage="done", percent=100, finished=_now(), lease_until=None):
        return "claim lost"
    return "succeeded"


def _forget_half_made_comparison(earlier_id: int, later_id: int):
    """The files an earlier attempt at this pair stored before it died (no comparison row names them yet)."""
    from .models import Comparison

    if Comparison.objects.filter(earlier_id=earlier_id, later_id=later_id).exists():
        return
    files = _comparison_files(f"{earlier_id}-{later_id}")
    if files:
        log.warning("comparison %s-%s: removing %d files an attempt that died left", earlier_id, later_id, len(files))
    for name in files:
        default_storage.delete(name)


# --- scheduled work ---------------------------------------------------------------

def flag_rigs_for_recalibration(now=None) -> list:
    """Rigs whose last calibration is older than their interval (or that have none) are flagged.

    Rigs whose cameras failed a stability check were flagged when it ran.
    Returns the serials newly flagged.
    """
    from .models import Rig

    now = now or _now()
    flagged = []
    for rig in Rig.objects.filter(needs_recalibration=False):
        last = rig.current_calibration
        if last is None:
            reason = "never calibrated"
        elif last.calibrated_at < now - timedelta(days=rig.recalibration_interval_days):
            age = (now - last.calibrated_at).days
            reason = f"last calibration is {age} days old (interval {rig.recalibration_interval_days} days)"
        else:
            continue
        if Rig.objects.filter(pk=rig.pk, needs_recalibration=False).update(
                needs_recalibration=True, recalibration_reason=reason):
            flagged.append(rig.serial)
    return flagged




def redispatch_stalled(older_than=None, now=None) -> list:
    """The outbox's sweeper and the claims' watchdog (Celery beat, or ``manage.py dispatch_queued``).

    Sends again every step the rows say is due and nobody is doing: a job
    queued but not claimed for ``JOB_REDISPATCH_SECONDS`` (its message never
    reached the broker, or the broker lost it), an arm or a registration
    handed over but not claimed as long, and a step whose claim's lease
    lapsed (its worker died). Each row is sent at most once per that period;
    a step delivered twice runs once (the claims), so sending too often is
    harmless. Returns what was sent, as ``(task name, job id[, arm])``.
    """
    from . import tasks

    now = now or _now()
    due = now - timedelta(seconds=settings.JOB_REDISPATCH_SECONDS if older_than is None else older_than)
    # a lapsed claim is sent at once (unless sent since it lapsed), then again once per period
    expired = Q(state=Job.RUNNING, lease_until__lt=now) & (Q(dispatched__lt=F("lease_until")) | Q(dispatched__lt=due))
    sent = []

    def resend(rows, row, task, *args):
        # a lapsed claim's first sending since it lapsed is a takeover (its worker died); a step taken over
        # JOB_MAX_TAKEOVERS times that dies again fails instead: a capture that kills its worker every time
        # would otherwise stay "running" for ever, and nobody would be told
        takeover = row.lease_until is not None and row.lease_until < now and row.dispatched < row.lease_until
        if takeover and row.takeovers >= settings.JOB_MAX_TAKEOVERS:
            why = (f"its worker stopped {row.takeovers + 1} times while running it (killed, e.g. out of memory on "
                   "this capture), so it was not sent again; the capture is kept: re-run the job once the cause is "
                   "mended")
            failed = {"state": Job.FAILED, "error": why, "lease_until": None, "dispatched": now,
                      **({"finished": now} if rows.model is Job else {})}  # an arm row has no finish time
            # the same election as below: one sweeper gives up
            if rows.filter(pk=row.pk, dispatched=row.dispatched, state=Job.RUNNING).update(**failed):
                log.error("giving up %s%r: %s", task.name, args, why)
            return
        extra = {"takeovers": F("takeovers") + 1} if takeover else {}
        # the conditional update elects one sweeper per row and period (several beats are harmless too)
        if rows.filter(pk=row.pk, dispatched=row.dispatched).update(dispatched=now, **extra):
            log.warning("re-dispatching %s%r (queued since %s, lease %s)", task.name, args, row.dispatched,
                        row.lease_until)
            if send(task, *args):
                sent.append((task.name, *args))

    for job in Job.objects.filter(state=Job.QUEUED, dispatched__lt=due):
        resend(Job.objects, job, _entry_task(job), job.pk)
    for job in Job.objects.filter(expired):
        if job.kind in (Job.CALIBRATION, Job.COMPARISON, Job.LANDMARKS):  # one step each: it starts again
            resend(Job.objects, job, _entry_task(job), job.pk)
        elif job.stage == "arms":  # died while starting, before the arms existed
            resend(Job.objects, job, tasks.start_reconstruction, job.pk)
        elif job.stage in REGISTRATION_STAGES:
            resend(Job.objects, job, tasks.register, job.pk)
    running = Job.objects.filter(state=Job.RUNNING, kind=Job.RECONSTRUCTION)
    for job in running.filter(stage="registration queued", dispatched__lt=due):
        resend(Job.objects, job, tasks.register, job.pk)
    for arm in ArmTask.objects.filter(Q(job__in=running.filter(stage="arms", lease_until=None))
                                      & (Q(state=Job.QUEUED, dispatched__lt=due) | expired)):
        resend(ArmTask.objects, arm, tasks.reconstruct_arm, arm.job_id, arm.arm)
    # the last arm's worker died between finishing its arm and handing over: hand over now
    for job in running.filter(stage="arms", lease_until=None).exclude(arms=None).exclude(
            arms__state__in=[Job.QUEUED, Job.RUNNING]):
        if arms_finished(job.pk):
            send(tasks.register, job.pk)
            sent.append((tasks.register.name, job.pk))
    return sent


def forget_comparisons_of(rec: Reconstruction) -> list:
    """The comparisons resting on ``rec`` (its landmarks changed), removed with their jobs; their files go once
    the transaction commits. Returns the pairs ``(earlier, later)`` to compare again
    (:func:`request_comparison`)."""
    from .models import Comparison

    pairs, files = [], []
    for c in Comparison.objects.filter(Q(earlier=rec) | Q(later=rec)).select_related("earlier", "later"):
        pairs.append((c.earlier, c.later))
        files += [c.deformation.name] if c.deformation else []
        files += list((c.pictures or {}).values())
        c.delete()
    jobs = Job.objects.filter(kind=Job.COMPARISON).filter(Q(earlier=rec) | Q(later=rec))
    # a pair still being compared (from the landmarks before) is compared again too: its result will be stale
    for j in jobs.filter(state__in=[Job.QUEUED, Job.RUNNING]).select_related("earlier", "later"):
        if all((j.earlier_id, j.later_id) != (e.pk, lt.pk) for e, lt in pairs):
            pairs.append((j.earlier, j.later))
    jobs.delete()
    transaction.on_commit(lambda: [default_storage.delete(f) for f in files if f])
    return pairs
