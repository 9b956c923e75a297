"""The clinic's records: who may see what, rigs and their calibrations, captures, jobs and results.

Every record hangs off a :class:`Clinic`; views scope their queries to the
clinics the user is a member of (404 for the rest). A rig authenticates with
its own :class:`RigKey` and may only upload for itself.
"""

import hashlib
import secrets
import uuid

from django.conf import settings
from django.db import models
from django.utils import timezone


class Clinic(models.Model):
    name = models.CharField(max_length=200, unique=True)
    created = models.DateTimeField(default=timezone.now)

    def __str__(self):
        return self.name


class Member(models.Model):
    CLINICIAN, TECHNICIAN, ADMINISTRATOR = "clinician", "technician", "administrator"
    ROLES = [(CLINICIAN, "Clinician"), (TECHNICIAN, "Technician"), (ADMINISTRATOR, "Administrator")]

    clinic = models.ForeignKey(Clinic, models.CASCADE, related_name="members")
    user = models.ForeignKey(settings.AUTH_USER_MODEL, models.CASCADE, related_name="memberships")
    role = models.CharField(max_length=20, choices=ROLES, default=CLINICIAN)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["clinic", "user"], name="one_membership_per_clinic")]

    def __str__(self):
        return f"{self.user} ({self.role}, {self.clinic})"


def clinics_of(user):
    """The clinics ``user`` may see (none for an anonymous user)."""
    if not user.is_authenticated:
        return Clinic.objects.none()
    return Clinic.objects.filter(members__user=user)


def captures_of(clinics, via: str = "") -> models.Q:
    """The condition that a capture session (reached through ``via``, e.g. ``"session"``) belongs to ``clinics``.

    A patient's capture belongs to the patient's clinic, wherever its rig has gone since; a capture with no
    visit (a test field's) to its rig's clinic. A rig handed to another clinic takes none of its patients'
    scans with it.
    """
    p = f"{via}__" if via else ""
    return (models.Q(**{f"{p}visit__patient__clinic__in": clinics})
            | models.Q(**{f"{p}visit__isnull": True, f"{p}rig__clinic__in": clinics}))


def jobs_of(clinics) -> models.Q:
    """The condition that a job belongs to ``clinics``: through its session (:func:`captures_of`: a comparison's
    and a landmark correction's session is its later torso's) or, without one, its rig's clinic."""
    return (models.Q(session__isnull=False) & captures_of(clinics, "session")) | models.Q(
        session__isnull=True, rig__clinic__in=clinics)


class Patient(models.Model):
    SEXES = [("F", "Female"), ("M", "Male"), ("X", "Other / not stated")]

    clinic = models.ForeignKey(Clinic, models.CASCADE, related_name="patients")
    identifier = models.CharField(max_length=64, help_text="The clinic's own patient number")
    name = models.CharField(max_length=200)
    date_of_birth = models.DateField(null=True, blank=True)
    sex = models.CharField(max_length=1, choices=SEXES, blank=True)
    notes = models.TextField(blank=True)
    created = models.DateTimeField(default=timezone.now)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["clinic", "identifier"], name="patient_identifier_per_clinic")]
        ordering = ["name"]

    def __str__(self):
        return f"{self.name} ({self.identifier})"


class Visit(models.Model):
    patient = models.ForeignKey(Patient, models.CASCADE, related_name="visits")
    date = models.DateField(default=timezone.localdate)
    clinician = models.ForeignKey(settings.AUTH_USER_MODEL, models.SET_NULL, null=True, blank=True,
                                  related_name="visits")
    reason = models.CharField(max_length=200, blank=True)
    notes = models.TextField(blank=True)
    next_visit_due = models.DateField(null=True, blank=True,
                                      help_text="When the patient should be seen again (the worklist's overdue list)")
    created = models.DateTimeField(default=timezone.now)

    class Meta:
        ordering = ["date", "id"]
        indexes = [
            # each patient's latest visit (the worklist's overdue list), read from the index alone
            models.Index(fields=["patient", "-date", "-id"], name="visit_latest_per_patient"),
            models.Index(fields=["date"], name="visit_date"),  # today's visits
        ]

    def __str__(self):
        return f"{self.patient} on {self.date}"


class Rig(models.Model):
    clinic = models.ForeignKey(Clinic, models.CASCADE, related_name="rigs")
    serial = models.CharField(max_length=64, unique=True)
    description = models.JSONField(help_text="rig.json as installed")
    recalibration_interval_days = models.PositiveIntegerField(default=30)
    poses_per_calibration = models.PositiveIntegerField(
        default=3, help_text="Test-field poses a calibration waits for (unless a session names its own count)")
    needs_recalibration = models.BooleanField(default=False)
    recalibration_reason = models.CharField(max_length=300, blank=True)
    created = models.DateTimeField(default=timezone.now)

    def __str__(self):
        return self.serial

    @property
    def current_calibration(self):
        return self.calibrations.filter(status=Calibration.SUCCEEDED).order_by("-calibrated_at", "-id").first()


class Camera(models.Model):
    rig = models.ForeignKey(Rig, models.CASCADE, related_name="cameras")
    name = models.CharField(max_length=32)
    arm = models.CharField(max_length=32)
    position = models.PositiveIntegerField(help_text="Order along the arm, from 0")
    width = models.PositiveIntegerField()
    height = models.PositiveIntegerField()
    pixel_size_mm = models.FloatField()
    nominal_focal_mm = models.FloatField()
    model = models.CharField(max_length=200, blank=True)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["rig", "name"], name="camera_name_per_rig")]
        ordering = ["rig", "arm", "position"]

    def __str__(self):
        return f"{self.rig.serial}/{self.name}"


def hash_key(key: str) -> str:
    # the keys are 256-bit random strings, so a fast hash cannot be brute-forced
    return hashlib.sha256(key.encode()).hexdigest()


class RigKey(models.Model):
    """An API key of one rig: only its hash is stored; the key is shown once, when made."""

    rig = models.ForeignKey(Rig, models.CASCADE, related_name="keys")
    prefix = models.CharField(max_length=16, help_text="The key's first characters, to recognise it")
    key_hash = models.CharField(max_length=64, unique=True)
    created = models.DateTimeField(default=timezone.now)
    revoked = models.DateTimeField(null=True, blank=True)
    last_used = models.DateTimeField(null=True, blank=True)

    def __str__(self):
        return f"{self.prefix}… ({self.rig.serial}{', revoked' if self.revoked else ''})"

    @classmethod
    def issue(cls, rig):
        """A new key for ``rig``: ``(RigKey, key)``. The plain key is never stored."""
        key = "tsk_" + secrets.token_urlsafe(32)
        return cls.objects.create(rig=rig, prefix=key[:10], key_hash=hash_key(key)), key

    @classmethod
    def lookup(cls, key: str):
        """The live key matching ``key``, or None."""
        if not key:
            return None
        return cls.objects.select_related("rig").filter(key_hash=hash_key(key), revoked__isnull=True).first()


class TestField(models.Model):
    clinic = models.ForeignKey(Clinic, models.CASCADE, related_name="testfields")
    name = models.CharField(max_length=200)
    description = models.JSONField(help_text="testfield.json as surveyed")
    created = models.DateTimeField(default=timezone.now)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["clinic", "name"], name="testfield_name_per_clinic")]

    def __str__(self):
        return self.name


class CaptureSession(models.Model):
    """One acquisition (a capture bundle) as the rig uploads it."""

    OPEN, FINALIZED, PARTIAL = "open", "finalized", "partial"
    STATES = [(OPEN, "Receiving images"), (FINALIZED, "Complete"), (PARTIAL, "Finalized with cameras missing")]

    uid = models.UUIDField(default=uuid.uuid4, unique=True, editable=False)
    rig = models.ForeignKey(Rig, models.CASCADE, related_name="sessions")
    kind = models.CharField(max_length=16, choices=[("torso", "Torso"), ("testfield", "Test field")])
    visit = models.ForeignKey(Visit, models.PROTECT, null=True, blank=True, related_name="sessions")
    testfield = models.ForeignKey(TestField, models.PROTECT, null=True, blank=True, related_name="sessions")
    pose = models.IntegerField(null=True, blank=True)
    calibration_set = models.CharField(max_length=100, blank=True,
                                       help_text="Test-field sessions calibrated together")
    poses_expected = models.PositiveIntegerField(null=True, blank=True)
    manifest = models.JSONField(help_text="capture.json as the rig sent it")
    manifest_sha256 = models.CharField(max_length=64)
    idempotency_key = models.CharField(max_length=200)
    captured_at = models.CharField(max_length=64)
    state = models.CharField(max_length=16, choices=STATES, default=OPEN)
    missing_cameras = models.JSONField(default=list, blank=True)
    needs_recalibration = models.BooleanField(
        default=False, help_text="The rig was flagged for recalibration when this capture arrived")
    created = models.DateTimeField(default=timezone.now)
    finalized = models.DateTimeField(null=True, blank=True)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["rig", "idempotency_key"], name="session_once_per_key")]
        ordering = ["-created"]

    def __str__(self):
        return f"{self.kind} session {self.uid} of {self.rig.serial}"


def image_path(instance, filename):
    return f"captures/{instance.session.rig.serial}/{instance.session.uid}/{filename}"


class CaptureImage(models.Model):
    session = models.ForeignKey(CaptureSession, models.CASCADE, related_name="images")
    camera = models.CharField(max_length=32)
    file_name = models.CharField(max_length=200, help_text="The image's path inside the bundle")
    sha256 = models.CharField(max_length=64)
    size = models.BigIntegerField(null=True, blank=True)
    file = models.FileField(upload_to=image_path, max_length=500, blank=True)
    received = models.DateTimeField(null=True, blank=True)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["session", "camera"], name="one_image_per_camera")]
        ordering = ["camera"]

    def __str__(self):
        return f"{self.camera} of {self.session}"


class Job(models.Model):
    """The durable state of a calibration, a reconstruction or a comparison: what a technician looks at."""

    CALIBRATION, RECONSTRUCTION, COMPARISON = "calibration", "reconstruction", "comparison"
    LANDMARKS = "landmarks"  # a torso's indices and pictures again, from a clinician's corrected landmarks
    KINDS = [(CALIBRATION, "Calibration"), (RECONSTRUCTION, "Reconstruction"), (COMPARISON, "Comparison"),
             (LANDMARKS, "Landmark correction")]
    QUEUED, RUNNING, SUCCEEDED, FAILED = "queued", "running", "succeeded", "failed"
    STATES = [(QUEUED, "Queued"), (RUNNING, "Running"), (SUCCEEDED, "Succeeded"), (FAILED, "Failed")]

    uid = models.UUIDField(default=uuid.uuid4, unique=True, editable=False)
    kind = models.CharField(max_length=20, choices=KINDS)
    rig = models.ForeignKey(Rig, models.CASCADE, related_name="jobs")
    session = models.ForeignKey(CaptureSession, models.CASCADE, null=True, blank=True, related_name="jobs",
                                help_text="The torso session (reconstruction) or the session that completed the set")
    sessions = models.ManyToManyField(CaptureSession, blank=True, related_name="calibration_jobs")
    calibration = models.ForeignKey("Calibration", models.PROTECT, null=True, blank=True, related_name="used_by",
                                    help_text="The calibration a reconstruction used")
    # a comparison asked for on its page: the two torsos (the session is the later torso's, so the job is the
    # patient's for the audit trail, an export and an erasure); a landmark correction: ``later``, the torso
    earlier = models.ForeignKey("Reconstruction", models.CASCADE, null=True, blank=True, related_name="+")
    later = models.ForeignKey("Reconstruction", models.CASCADE, null=True, blank=True, related_name="+")
    state = models.CharField(max_length=16, choices=STATES, default=QUEUED)
    stage = models.CharField(max_length=40, blank=True)
    percent = models.PositiveSmallIntegerField(default=0)
    error = models.TextField(blank=True)
    attempt = models.PositiveIntegerField(default=0, help_text="Runs started (re-runs included)")
    takeovers = models.PositiveSmallIntegerField(
        default=0, help_text="Times a step was sent again because its worker stopped holding it (since the last run)")
    claimed = models.DateTimeField(null=True, blank=True, help_text="When the step now running claimed the job")
    lease_until = models.DateTimeField(
        null=True, blank=True,
        help_text="The running step's claim holds until then (renewed while it works); past it, the step is redone")
    dispatched = models.DateTimeField(default=timezone.now,
                                      help_text="When the job's next step was last handed to the broker")
    created = models.DateTimeField(default=timezone.now)
    started = models.DateTimeField(null=True, blank=True)
    finished = models.DateTimeField(null=True, blank=True)

    @property
    def clinic_id(self):
        """The clinic the job belongs to (:func:`jobs_of`): its session's patient's, else its rig's."""
        visit = self.session.visit if self.session_id else None
        return visit.patient.clinic_id if visit is not None else self.rig.clinic_id

    class Meta:
        ordering = ["-created"]
        constraints = [
            # two requests for the same comparison at once make one job (the second gets the first's)
            models.UniqueConstraint(fields=["earlier", "later"], condition=models.Q(kind="comparison"),
                                    name="one_comparison_job_per_pair")]

    def __str__(self):
        return f"{self.kind} job {self.uid} ({self.state})"


def result_path(instance, filename):
    return f"results/{instance.job.uid}/{filename}"


class ArmTask(models.Model):
    """One arm of a reconstruction job; the arms run in parallel and join through these rows."""

    job = models.ForeignKey(Job, models.CASCADE, related_name="arms")
    arm = models.CharField(max_length=32)
    state = models.CharField(max_length=16, choices=Job.STATES, default=Job.QUEUED)
    claimed = models.DateTimeField(null=True, blank=True)
    lease_until = models.DateTimeField(null=True, blank=True, help_text="As the job's: the arm's claim holds until then")
    takeovers = models.PositiveSmallIntegerField(default=0, help_text="As the job's, for this arm")
    dispatched = models.DateTimeField(default=timezone.now, help_text="When the arm was last handed to the broker")
    surface = models.FileField(upload_to=result_path, max_length=500, blank=True)
    report = models.JSONField(null=True, blank=True)
    error = models.TextField(blank=True)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["job", "arm"], name="one_task_per_arm")]
        ordering = ["arm"]


class Calibration(models.Model):
    SUCCEEDED, FAILED = "succeeded", "failed"

    rig = models.ForeignKey(Rig, models.CASCADE, related_name="calibrations")
    job = models.OneToOneField(Job, models.SET_NULL, null=True, blank=True, related_name="calibration_result")
    file = models.FileField(upload_to="calibrations/", max_length=500, help_text="calibration.json")
    calibrated_at = models.DateTimeField(default=timezone.now)
    status = models.CharField(max_length=16, default=SUCCEEDED)
    figures = models.JSONField(default=dict, help_text="Residuals, targets used and dropped, warnings")
    sigmas = models.JSONField(default=dict, help_text="Posterior standard deviations per camera")

    class Meta:
        ordering = ["-calibrated_at", "-id"]

    def __str__(self):
        return f"calibration of {self.rig.serial} at {self.calibrated_at:%Y-%m-%d %H:%M}"


class StabilityCheck(models.Model):
    camera = models.ForeignKey(Camera, models.CASCADE, related_name="stability_checks")
    calibration = models.ForeignKey(Calibration, models.CASCADE, related_name="stability_checks")
    reference = models.ForeignKey(Calibration, models.CASCADE, related_name="+",
                                  help_text="The earlier calibration it was compared against")
    zrot_px = models.FloatField()
    rot_px = models.FloatField()
    spr_px = models.FloatField()
    arm_px = models.FloatField(null=True, blank=True,
                               help_text="The camera's bundle in its arm's frame (needs two other cameras of the arm)")
    threshold_px = models.FloatField(help_text="The largest of the measures' thresholds")
    thresholds = models.JSONField(default=dict, blank=True, help_text="Each measure's threshold (px)")
    exceeds = models.JSONField(default=list, blank=True, help_text="The measures above their threshold")
    stable = models.BooleanField()
    created = models.DateTimeField(default=timezone.now)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["camera", "calibration", "reference"],
                                               name="one_check_per_camera_and_pair")]
        ordering = ["camera", "created"]


class Reconstruction(models.Model):
    job = models.OneToOneField(Job, models.CASCADE, related_name="reconstruction")
    session = models.ForeignKey(CaptureSession, models.CASCADE, related_name="reconstructions")
    torso = models.FileField(upload_to=result_path, max_length=500, help_text="torso.ply")
    mesh = models.FileField(upload_to=result_path, max_length=500, blank=True, help_text="torso-mesh.ply")
    report_file = models.FileField(upload_to=result_path, max_length=500, help_text="report.json")
    report = models.JSONField()
    status = models.CharField(max_length=16, help_text="ok, partial or failed, as the engine judged it")
    points = models.PositiveIntegerField()
    indices = models.JSONField(null=True, blank=True, help_text="torso-indices/1 of this torso")
    landmarks = models.JSONField(null=True, blank=True,
                                 help_text="A clinician's corrections: vertebra_prominens, sacral_point, dimple_left, "
                                           "dimple_right (mm, rig frame)")
    landmark_history = models.JSONField(
        default=list, blank=True,
        help_text="The corrections replaced, newest last: {landmarks, by, at}; undo restores the last")
    pictures = models.JSONField(default=dict, blank=True, help_text="Picture name -> storage name")
    created = models.DateTimeField(default=timezone.now)

    class Meta:
        ordering = ["-created"]


class Comparison(models.Model):
    """A later visit's torso against an earlier one (filled by the analysis)."""

    earlier = models.ForeignKey(Reconstruction, models.CASCADE, related_name="+")
    later = models.ForeignKey(Reconstruction, models.CASCADE, related_name="comparisons")
    report = models.JSONField(default=dict)
    deformation = models.FileField(upload_to="comparisons/", max_length=500, blank=True)
    pictures = models.JSONField(default=dict, blank=True, help_text="Picture name -> storage name")
    created = models.DateTimeField(default=timezone.now)
    repeat = models.BooleanField(default=False, editable=False,
                                 help_text="Two scans of one visit (is_repeat), kept on save: the pages find the "
                                           "clinic's repeat pairs by it without joining every comparison")

    @property
    def is_repeat(self):
        """Two captures of one visit: a repeatability pair, not a change."""
        return self.earlier.session.visit_id == self.later.session.visit_id

    def save(self, *args, **kwargs):
        self.repeat = self.is_repeat
        if kwargs.get("update_fields") is not None:
            kwargs["update_fields"] = {*kwargs["update_fields"], "repeat"}
        super().save(*args, **kwargs)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["earlier", "later"], name="one_comparison_per_pair")]
        indexes = [models.Index(fields=["later"], condition=models.Q(repeat=True), name="comparison_repeat_pairs")]
        ordering = ["-created"]


class AuditTrailError(Exception):
    """An attempt to rewrite the audit trail: it is append-only."""


class AuditQuerySet(models.QuerySet):
    # the application may only add to the trail; bulk rewrites are refused like single ones
    def update(self, **kwargs):
        raise AuditTrailError("audit events cannot be changed")

    def delete(self):
        raise AuditTrailError("audit events cannot be deleted")


class AuditEvent(models.Model):
    """Who viewed, downloaded, created, changed or deleted which patient's data, when and from where.

    Written by ``clinic/audit.py``. The patient is an integer copy, not a
    foreign key, so a patient's trail outlives the patient's erasure; the
    user's name is copied for the same reason.
    """

    VIEW, DOWNLOAD, CREATE, CHANGE, DELETE = "view", "download", "create", "change", "delete"
    EXPORT, ERASE, LOGIN, LOGIN_FAILED = "export", "erase", "login", "login_failed"
    ACTIONS = [(VIEW, "View"), (DOWNLOAD, "Download"), (CREATE, "Create"), (CHANGE, "Change"), (DELETE, "Delete"),
               (EXPORT, "Export"), (ERASE, "Erase"), (LOGIN, "Sign-in"), (LOGIN_FAILED, "Failed sign-in")]

    time = models.DateTimeField(default=timezone.now, db_index=True)
    user = models.ForeignKey(settings.AUTH_USER_MODEL, models.SET_NULL, null=True, blank=True, related_name="+")
    username = models.CharField(max_length=150, blank=True, db_index=True)
    rig_serial = models.CharField(max_length=64, blank=True, help_text="The rig whose key made the request")
    # no database constraint: the trail keeps the clinic's id after the clinic is deleted (as it keeps the
    # patient's), and the deletion's own events (written while it cascades) may name it
    clinic = models.ForeignKey(Clinic, models.DO_NOTHING, null=True, blank=True, related_name="+",
                               db_constraint=False)
    patient_id = models.BigIntegerField(null=True, blank=True, db_index=True)
    action = models.CharField(max_length=16, choices=ACTIONS)
    object_type = models.CharField(max_length=40, blank=True)
    object_id = models.CharField(max_length=64, blank=True)
    path = models.CharField(max_length=500, blank=True)
    method = models.CharField(max_length=10, blank=True)
    status = models.PositiveSmallIntegerField(null=True, blank=True)
    remote_addr = models.GenericIPAddressField(null=True, blank=True)
    detail = models.JSONField(default=dict, blank=True, help_text="e.g. the rows and files an erasure removed")

    objects = AuditQuerySet.as_manager()

    class Meta:
        ordering = ["-time", "-id"]

    def __str__(self):
        who = self.username or self.rig_serial or "system"
        return f"{self.time:%Y-%m-%d %H:%M:%S} {who} {self.action} {self.object_type} {self.object_id}".rstrip()

    def save(self, *args, **kwargs):
        if not self._state.adding:
            raise AuditTrailError("audit events cannot be changed")
        kwargs["force_insert"] = True  # never an UPDATE, even with an explicit primary key
        super().save(*args, **kwargs)

    def delete(self, *args, **kwargs):
        raise AuditTrailError("audit events cannot be deleted")
