"""The Django admin: every record of every clinic, so for superusers only.

Clinic administrators manage their own clinic's members and rig keys on the
clinic's pages (``clinic/views.py``), which are scoped to their clinics.
"""

from django import forms
from django.contrib import admin, messages
from django.contrib.admin.forms import AdminAuthenticationForm

from . import pipeline
from .models import (ArmTask, AuditEvent, Calibration, Camera, CaptureImage, CaptureSession, Clinic, Comparison, Job, Member,
                     Patient, Reconstruction, Rig, RigKey, StabilityCheck, TestField, Visit)


class MemberInline(admin.TabularInline):
    model = Member
    extra = 0
    autocomplete_fields = ["user"]


@admin.register(Clinic)
class ClinicAdmin(admin.ModelAdmin):
    list_display = ["name", "created"]
    search_fields = ["name"]
    inlines = [MemberInline]


class VisitInline(admin.TabularInline):
    model = Visit
    extra = 0
    fields = ["date", "clinician", "reason"]


@admin.register(Patient)
class PatientAdmin(admin.ModelAdmin):
    list_display = ["identifier", "name", "date_of_birth", "sex", "clinic"]
    list_filter = ["clinic", "sex"]
    search_fields = ["identifier", "name"]
    inlines = [VisitInline]


@admin.register(Visit)
class VisitAdmin(admin.ModelAdmin):
    list_display = ["patient", "date", "clinician", "reason"]
    list_filter = ["date"]
    search_fields = ["patient__name", "patient__identifier"]
    date_hierarchy = "date"


class CameraInline(admin.TabularInline):
    model = Camera
    extra = 0
    readonly_fields = ["name", "arm", "position", "width", "height", "pixel_size_mm", "nominal_focal_mm", "model"]
    can_delete = False


class RigKeyInline(admin.TabularInline):
    model = RigKey
    extra = 0
    fields = ["prefix", "created", "last_used", "revoked"]
    readonly_fields = ["prefix", "created", "last_used"]
    can_delete = False


@admin.register(Rig)
class RigAdmin(admin.ModelAdmin):
    list_display = ["serial", "clinic", "needs_recalibration", "recalibration_reason", "recalibration_interval_days"]
    list_filter = ["clinic", "needs_recalibration"]
    search_fields = ["serial"]
    inlines = [CameraInline, RigKeyInline]
    actions = ["issue_key"]

    @admin.action(description="Issue a new API key (shown once)")
    def issue_key(self, request, queryset):
        for rig in queryset:
            _, key = RigKey.issue(rig)
            self.message_user(request, f"New key for {rig.serial}: {key} (store it now: it is not shown again)",
                              messages.WARNING)


@admin.register(RigKey)
class RigKeyAdmin(admin.ModelAdmin):
    list_display = ["prefix", "rig", "created", "last_used", "revoked"]
    list_filter = ["rig"]
    readonly_fields = ["prefix", "key_hash", "rig", "created", "last_used"]
    actions = ["revoke"]

    def has_add_permission(self, request):
        return False  # keys are issued from the rig's page, so the plain key can be shown once

    @admin.action(description="Revoke the selected keys")
    def revoke(self, request, queryset):
        from django.utils import timezone

        n = queryset.filter(revoked__isnull=True).update(revoked=timezone.now())
        self.message_user(request, f"{n} key(s) revoked")


@admin.register(TestField)
class TestFieldAdmin(admin.ModelAdmin):
    list_display = ["name", "clinic", "created"]


class CaptureImageInline(admin.TabularInline):
    model = CaptureImage
    extra = 0
    readonly_fields = ["camera", "file_name", "sha256", "size", "file", "received"]
    can_delete = False


@admin.register(CaptureSession)
class CaptureSessionAdmin(admin.ModelAdmin):
    list_display = ["uid", "rig", "kind", "state", "visit", "pose", "needs_recalibration", "created"]
    list_filter = ["kind", "state", "rig", "needs_recalibration"]
    readonly_fields = ["uid", "manifest", "manifest_sha256", "idempotency_key", "missing_cameras"]
    inlines = [CaptureImageInline]


class ArmTaskInline(admin.TabularInline):
    model = ArmTask
    extra = 0
    readonly_fields = ["arm", "state", "error"]
    fields = ["arm", "state", "error"]
    can_delete = False


@admin.register(Job)
class JobAdmin(admin.ModelAdmin):
    list_display = ["uid", "kind", "rig", "state", "stage", "percent", "attempt", "created", "finished"]
    list_filter = ["kind", "state", "rig"]
    readonly_fields = ["uid", "error"]
    inlines = [ArmTaskInline]
    actions = ["rerun"]

    @admin.action(description="Re-run the selected jobs")
    def rerun(self, request, queryset):
        for job in queryset:
            try:
                pipeline.rerun(job)
                self.message_user(request, f"job {job.uid} queued again")
            except pipeline.JobError as exc:
                self.message_user(request, str(exc), messages.ERROR)


@admin.register(Calibration)
class CalibrationAdmin(admin.ModelAdmin):
    list_display = ["rig", "calibrated_at", "status"]
    list_filter = ["rig", "status"]


@admin.register(StabilityCheck)
class StabilityCheckAdmin(admin.ModelAdmin):
    list_display = ["camera", "calibration", "reference", "zrot_px", "rot_px", "spr_px", "arm_px", "threshold_px", "stable"]
    list_filter = ["stable", "camera__rig"]


@admin.register(Reconstruction)
class ReconstructionAdmin(admin.ModelAdmin):
    list_display = ["session", "status", "points", "created"]
    list_filter = ["status"]


@admin.register(Comparison)
class ComparisonAdmin(admin.ModelAdmin):
    list_display = ["earlier", "later", "created"]


@admin.register(AuditEvent)
class AuditEventAdmin(admin.ModelAdmin):
    """The audit trail, to read: the application only ever appends to it (``clinic/audit.py``)."""

    list_display = ["time", "username", "rig_serial", "action", "patient_id", "object_type", "object_id", "method",
                    "path", "status", "remote_addr"]
    list_filter = ["action", "clinic", "time"]
    search_fields = ["=patient_id", "username", "rig_serial", "path", "remote_addr"]
    date_hierarchy = "time"

    def has_view_permission(self, request, obj=None):
        return request.user.is_active and request.user.is_superuser

    def has_add_permission(self, request):
        return False

    def has_change_permission(self, request, obj=None):
        return False

    def has_delete_permission(self, request, obj=None):
        return False


def _superusers_only(request):
    return request.user.is_active and request.user.is_superuser


class SuperuserAuthenticationForm(AdminAuthenticationForm):
    """The admin's sign-in: staff that are not superusers are refused here too, not signed in and bounced."""

    def confirm_login_allowed(self, user):
        super().confirm_login_allowed(user)
        if not user.is_superuser:
            raise forms.ValidationError("The admin is for superusers; your clinic's pages are at /.",
                                        code="not_superuser")


admin.site.has_permission = _superusers_only
admin.site.login_form = SuperuserAuthenticationForm
