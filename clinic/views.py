"""The clinicians' pages: patients, a patient's history, a visit, a comparison, a rig.

Every query goes through ``clinics_of(request.user)``: anything outside the
user's clinics is a 404. What a member may change depends on their role, and
the pages ask the API's rule (below), so a page never allows what the API
forbids. Pages are plain HTML (a running job's page refreshes itself with a
meta tag, no JavaScript needed).
"""

import io
import json
import tempfile
from pathlib import Path

from django.contrib import messages
from django.contrib.auth import get_user_model
from django.contrib.auth.decorators import login_required
from django.core.exceptions import PermissionDenied
from django.core.files.storage import default_storage
from django.db import connection, transaction
from django.db.models import Q
from django.http import FileResponse, Http404, HttpResponse, JsonResponse
from django.shortcuts import get_object_or_404, redirect, render
from django.urls import reverse
from django.views.decorators.http import require_POST

from . import api
from .models import Comparison, Job, Member, Patient, Reconstruction, Rig, Visit, clinics_of

# Who may do what. Actions the API has (re-running a job, issuing and revoking a rig's keys) are run through
# the API's own operations, so the pages get its scoping, its role check (`_member_clinic`, administrators and
# technicians) and its logic. Actions only the pages have ask the same helper with these roles:
CORRECT_LANDMARKS = (Member.CLINICIAN, Member.ADMINISTRATOR)  # a clinical judgement: not technicians
MANAGE_MEMBERS = (Member.ADMINISTRATOR,)


def _require_role(request, clinic_id, roles=None):
    """The clinic, if the user's role in it allows the action: 404 for a non-member, 403 for another role."""
    try:
        if roles is None:  # the API's default: what its staff endpoints allow
            return api._member_clinic(request, clinic_id)
        return api._member_clinic(request, clinic_id, roles=roles)
    except api.ApiError as exc:
        raise (Http404 if exc.status == 404 else PermissionDenied)(exc.detail) from None


def _may(request, clinic_id, roles=None) -> bool:
    """Whether to offer the action on a page (the action itself checks again)."""
    try:
        _require_role(request, clinic_id, roles)
    except (Http404, PermissionDenied):
        return False
    return True


def _run_api(operation, request, *args):
    """One of the API's staff operations for a page: its 404 and 403 become the page's; other refusals stay ApiError."""
    try:
        out = operation(request, *args)
    except api.ApiError as exc:
        if exc.status in (403, 404):
            raise (Http404 if exc.status == 404 else PermissionDenied)(exc.detail) from None
        raise
    return json.loads(out.content) if isinstance(out, HttpResponse) else out


def _refused(request, message, status, back=None):
    return render(request, "clinic/error.html", {"message": message, "back": back}, status=status)


def healthz(request):
    """Liveness for load balancers: the app answers and reaches its database."""
    try:
        with connection.cursor() as cursor:
            cursor.execute("SELECT 1")
        database = True
    except Exception:  # any database failure means "not healthy", not a 500
        database = False
    return JsonResponse({"status": "ok" if database else "degraded", "database": database},
                        status=200 if database else 503)


# the indices shown in tables and trends: (key in the flattened torso-indices/1, label, unit)
INDEX_ROWS = [
    ("lateral_deviation_mm.max", "Lateral deviation of the symmetry line, max", "mm"),
    ("lateral_deviation_mm.rms", "Lateral deviation of the symmetry line, RMS", "mm"),
    ("surface_rotation_deg.max", "Surface rotation, max", "°"),
    ("surface_rotation_deg.rms", "Surface rotation, RMS", "°"),
    ("spine_lateral_deviation_mm.max", "Spine midline deviation (model), max", "mm"),
    ("midline_rotation_deg.max", "Rotation of the skin at the symmetry line, max", "°"),
    ("hump_mm", "Rib / lumbar hump", "mm"),
    ("trunk_imbalance_mm", "Trunk imbalance", "mm"),
    ("asymmetry_mm", "Asymmetry (mirror)", "mm"),
    ("trunk_length_mm", "Trunk length VP–SP", "mm"),
]


def _flat(indices):
    from analysis.repeatability import flatten

    return flatten(indices or {})


def _patients(user):
    return Patient.objects.filter(clinic__in=clinics_of(user))


def _reconstructions(user):
    return Reconstruction.objects.filter(session__rig__clinic__in=clinics_of(user))


def _best(visit):
    """The visit's torso shown to clinicians: its latest good reconstruction (or None)."""
    return (Reconstruction.objects.filter(session__visit=visit, status__in=["ok", "partial"],
                                          job__state=Job.SUCCEEDED).order_by("-created").first())


def _mdc(clinic):
    from .analysis_step import clinic_mdc

    return clinic_mdc(clinic)


def _noise(clinic) -> dict:
    """What the noise verdicts rest on: the clinic's repeat pairs and how many are needed before any flag."""
    from analysis.repeatability import MIN_REPEAT_PAIRS

    from .analysis_step import repeat_pairs

    return {"pairs": repeat_pairs(clinic), "needed": MIN_REPEAT_PAIRS}


@login_required
def patients(request):
    """The patients of the user's clinics, with a search by name or identifier."""
    q = request.GET.get("q", "").strip()
    rows = _patients(request.user).select_related("clinic")
    if q:
        rows = rows.filter(Q(name__icontains=q) | Q(identifier__icontains=q))
    rigs = Rig.objects.filter(clinic__in=clinics_of(request.user))
    administered = [c for c in clinics_of(request.user) if _may(request, c.pk, MANAGE_MEMBERS)]
    return render(request, "clinic/patients.html", {"patients": rows, "q": q, "rigs": rigs,
                                                    "administered": administered})


@login_required
def patient(request, patient_id):
    """A patient's history: visits on a timeline, index trends with their MDC band, the latest pictures."""
    p = get_object_or_404(_patients(request.user), pk=patient_id)
    visits = []
    for v in p.visits.all():
        rec = _best(v)
        jobs = Job.objects.filter(session__visit=v).order_by("-created")
        visits.append({"visit": v, "rec": rec, "job": jobs.first(), "flat": _flat(rec.indices if rec else None)})
    mdc = _mdc(p.clinic)
    rows = []
    for key, label, unit in INDEX_ROWS:
        vals = [x["flat"].get(key) for x in visits]
        m = (mdc.get(key) or {}).get("mdc")
        first = next((v for v in vals if v is not None), None)
        rows.append({"label": label, "unit": unit, "mdc": m,
                     "cells": [{"value": v, "beyond": (v is not None and first is not None and m is not None
                                                       and abs(v - first) > m)} for v in vals]})
    latest = next((x["rec"] for x in reversed(visits) if x["rec"]), None)
    with_torso = [x["visit"] for x in visits if x["rec"]]
    return render(request, "clinic/patient.html", {
        "patient": p, "visits": visits, "rows": rows, "latest": latest, "with_torso": with_torso,
        "noise": _noise(p.clinic),
        "earlier_default": with_torso[0].pk if with_torso else None,
        "later_default": with_torso[-1].pk if with_torso else None})


@login_required
def patient_trend(request, patient_id):
    """The trend plot of every index over the patient's visits (PNG, drawn on request)."""
    from analysis.pictures import trend_picture

    p = get_object_or_404(_patients(request.user), pk=patient_id)
    series = [(str(v.date), rec.indices) for v in p.visits.all() if (rec := _best(v)) and rec.indices]
    if not series:
        raise Http404("no visit with a torso yet")
    mdc = {k: v["mdc"] for k, v in _mdc(p.clinic).items()}
    with tempfile.TemporaryDirectory() as tmp:
        png = trend_picture(series, Path(tmp) / "trend.png", mdc=mdc)
        data = Path(png).read_bytes()
    return HttpResponse(data, content_type="image/png")


@login_required
def visit(request, visit_id):
    """A visit: torso pictures, the reconstruction's quality figures, indices, the job's progress."""
    v = get_object_or_404(Visit.objects.filter(patient__clinic__in=clinics_of(request.user)), pk=visit_id)
    rec = _best(v)
    jobs = list(Job.objects.filter(session__visit=v).order_by("-created"))
    running = any(j.state in (Job.QUEUED, Job.RUNNING) for j in jobs)
    report = rec.report if rec else {}
    pairs = report.get("registration", {}).get("pairs", [])
    arms = {a: {"points": r.get("points"), "sigma": r.get("sigma_mm_median")} for a, r in report.get("arms", {}).items()}
    return render(request, "clinic/visit.html", {
        "visit": v, "rec": rec, "jobs": jobs, "running": running, "pairs": pairs, "arms": arms,
        "flat": _flat(rec.indices if rec else None), "index_rows": INDEX_ROWS,
        "landmarks": (rec.indices or {}).get("landmarks", {}) if rec else {},
        "may_rerun": _may(request, v.patient.clinic_id),
        "may_correct": _may(request, v.patient.clinic_id, CORRECT_LANDMARKS)})


@login_required
@require_POST
def correct_landmarks(request, visit_id):
    """A clinician moves the vertebra prominens or the sacral point; the indices are computed again."""
    from .analysis_step import analyse_reconstruction

    v = get_object_or_404(Visit.objects.filter(patient__clinic__in=clinics_of(request.user)), pk=visit_id)
    _require_role(request, v.patient.clinic_id, CORRECT_LANDMARKS)
    rec = _best(v)
    if rec is None:
        raise Http404("this visit has no torso yet")
    landmarks = {}
    for name in ("vertebra_prominens", "sacral_point"):
        raw = request.POST.get(name, "").strip()
        if raw:
            try:
                xyz = [float(t) for t in raw.replace(",", " ").split()]
            except ValueError:
                xyz = []
            if len(xyz) != 3:
                return render(request, "clinic/error.html", {
                    "message": f"{name.replace('_', ' ')}: give three numbers x y z in mm, got {raw!r}"}, status=400)
            landmarks[name] = xyz
    rec.landmarks = landmarks or None
    rec.save(update_fields=["landmarks"])
    analyse_reconstruction(rec)
    return redirect("visit", visit_id=v.pk)


@login_required
def comparison(request, patient_id):
    """Two chosen visits: deformation map, per-region changes, index changes flagged against the MDC."""
    from analysis.repeatability import index_changes

    from .analysis_step import compare_reconstructions

    p = get_object_or_404(_patients(request.user), pk=patient_id)
    try:
        earlier_v = get_object_or_404(p.visits, pk=int(request.GET.get("earlier", "")))
        later_v = get_object_or_404(p.visits, pk=int(request.GET.get("later", "")))
    except ValueError:
        raise Http404("choose two visits") from None
    if (later_v.date, later_v.pk) < (earlier_v.date, earlier_v.pk):
        earlier_v, later_v = later_v, earlier_v
    earlier, later = _best(earlier_v), _best(later_v)
    if earlier is None or later is None or earlier == later:
        raise Http404("both visits need a reconstructed torso")
    comp = compare_reconstructions(earlier, later)
    mdc = _mdc(p.clinic)
    facing = comp.report.get("facing") or {}
    changes = index_changes(earlier.indices or {}, later.indices or {}, mdc,
                            sides_agree=facing.get("consistent", True))
    labels = {k: (label, unit) for k, label, unit in INDEX_ROWS}
    index_rows = [{"label": labels.get(k, (k, ""))[0], "unit": labels.get(k, ("", ""))[1], **c}
                  for k, c in changes.items()]
    regions = []
    for name, stats in (comp.report.get("regions") or {}).items():
        m = (mdc.get(f"regions.{name}.mean") or {}).get("mdc")
        mean = stats.get("mean")
        regions.append({"name": name.replace("_", " "), **stats, "mdc": m,
                        "beyond": None if m is None or mean is None else abs(mean) > m})
    return render(request, "clinic/comparison.html", {
        "patient": p, "earlier": earlier_v, "later": later_v, "comparison": comp, "report": comp.report,
        "regions": regions, "index_rows": index_rows, "facing": facing, "noise": _noise(p.clinic), "growth": comp.report.get("growth"),
        "repeat": comp.is_repeat})


@login_required
def rig(request, serial):
    """A rig: its calibrations, every camera's stability history and, for who may manage them, its API keys."""
    return _rig_page(request, get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)),
                                                serial=serial))


def _rig_page(request, r, new_key=None):
    calibrations = list(r.calibrations.all().order_by("calibrated_at"))
    cams = []
    for cam in r.cameras.all():
        checks = list(cam.stability_checks.select_related("calibration").order_by("calibration__calibrated_at"))
        cams.append({"camera": cam, "checks": checks, "last": checks[-1] if checks else None})
    cal_rows = []
    for c in calibrations:
        rms = [v for v in (c.figures.get("residual_rms_px") or {}).values() if v is not None]
        cal_rows.append({"calibration": c, "sigma0": c.figures.get("sigma0"),
                         "rms_max": max(rms) if rms else None,
                         "dropped": sum((c.figures.get("dropped") or {}).values()),
                         "warnings": len(c.figures.get("warnings") or [])})
    may_manage_keys = _may(request, r.clinic_id)
    return render(request, "clinic/rig.html", {
        "rig": r, "calibrations": cal_rows, "cameras": cams, "has_checks": any(c["checks"] for c in cams),
        "may_manage_keys": may_manage_keys, "keys": r.keys.order_by("-created") if may_manage_keys else [],
        "new_key": new_key})


@login_required
@require_POST
def issue_rig_key(request, serial):
    """A new API key for the rig, shown on this one answer only (only its hash is kept)."""
    issued = _run_api(api.new_rig_key, request, serial)
    r = get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)), serial=serial)
    return _rig_page(request, r, new_key=issued["key"])


@login_required
@require_POST
def revoke_rig_key(request, serial, prefix):
    _run_api(api.revoke_rig_key, request, serial, prefix)
    messages.success(request, f"Key {prefix}… revoked: the rig can no longer upload with it.")
    return redirect("rig", serial=serial)


@login_required
def rig_stability_chart(request, serial):
    """Every measure of every camera over the rig's calibrations against its threshold (SVG, drawn on request)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)), serial=serial)
    cams = [c for c in r.cameras.all() if c.stability_checks.exists()]
    if not cams:
        raise Http404("no stability check yet")
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.6), sharex=True)
    measures = (("zrot_px", "ZROT"), ("rot_px", "ROT"), ("spr_px", "SPR"), ("arm_px", "ARM"))
    for ax, (field, title) in zip(axes, measures):
        for cam in cams:
            checks = [c for c in cam.stability_checks.select_related("calibration").order_by("calibration__calibrated_at")
                      if getattr(c, field) is not None]
            xs = [c.calibration.calibrated_at for c in checks]
            ys = [getattr(c, field) / (c.thresholds or {}).get(field, c.threshold_px) for c in checks]
            ax.plot(xs, ys, "o-", lw=1, ms=3, label=cam.name)
        ax.axhline(1.0, color="#c0392b", lw=1, ls="--")
        ax.set_title(f"{title} / threshold (above 1: unstable)", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[-1].legend(fontsize=6, ncol=2, loc="upper left", bbox_to_anchor=(1.02, 1))
    fig.autofmt_xdate()
    fig.tight_layout()
    buf = io.StringIO()
    fig.savefig(buf, format="svg")
    plt.close(fig)
    return HttpResponse(buf.getvalue(), content_type="image/svg+xml")


@login_required
def picture(request, kind, pk, name):
    """A stored picture of a reconstruction or a comparison the user may see."""
    if kind == "reconstruction":
        obj = get_object_or_404(_reconstructions(request.user), pk=pk)
    elif kind == "comparison":
        obj = get_object_or_404(Comparison.objects.filter(later__session__rig__clinic__in=clinics_of(request.user)),
                                pk=pk)
    else:
        raise Http404(kind)
    stored = (obj.pictures or {}).get(name)
    if not stored or not default_storage.exists(stored):
        raise Http404(f"no picture {name!r}")
    return FileResponse(default_storage.open(stored, "rb"), content_type="image/png")


@login_required
@require_POST
def rerun(request, job_id):
    job = get_object_or_404(Job.objects.filter(rig__clinic__in=clinics_of(request.user)), uid=job_id)
    target = reverse("visit", args=[job.session.visit_id]) if job.session and job.session.visit_id else "/"
    try:
        _run_api(api.rerun_job, request, str(job.uid))
    except api.ApiError as exc:  # 409: a worker still holds it
        return _refused(request, exc.detail, exc.status, back=target)
    return redirect(target)


# --- a clinic's members, for its administrators ---------------------------------------------

@login_required
def members(request, clinic_id):
    clinic = _require_role(request, clinic_id, MANAGE_MEMBERS)
    return render(request, "clinic/members.html", {
        "clinic": clinic, "members": clinic.members.select_related("user").order_by("user__username"),
        "roles": Member.ROLES})


def _role(request):
    role = request.POST.get("role", "")
    return role if role in dict(Member.ROLES) else None


def _keeps_an_administrator(clinic, member, role=None) -> bool:
    """Whether the clinic still has an administrator once ``member`` is removed (or given ``role``)."""
    if member.role != Member.ADMINISTRATOR or role == Member.ADMINISTRATOR:
        return True
    # locked, so two administrators cannot demote each other at once and leave none
    admins = list(clinic.members.select_for_update().filter(role=Member.ADMINISTRATOR).values_list("pk", flat=True))
    return any(pk != member.pk for pk in admins)


@login_required
@require_POST
def add_member(request, clinic_id):
    """An existing user joins the clinic with a role (accounts themselves are made by a superuser)."""
    clinic = _require_role(request, clinic_id, MANAGE_MEMBERS)
    back = reverse("members", args=[clinic.pk])
    username, role = request.POST.get("username", "").strip(), _role(request)
    if role is None:
        return _refused(request, "choose a role", 400, back)
    user = get_user_model().objects.filter(username=username, is_active=True).first()
    if user is None:
        return _refused(request, f"there is no active user {username!r}; ask your superuser to create the account",
                        400, back)
    _, created = Member.objects.get_or_create(clinic=clinic, user=user, defaults={"role": role})
    if not created:
        return _refused(request, f"{username} is already a member of {clinic.name}; change their role instead",
                        409, back)
    messages.success(request, f"{username} added as {role}.")
    return redirect(back)


@login_required
@require_POST
def change_member_role(request, clinic_id, member_id):
    clinic = _require_role(request, clinic_id, MANAGE_MEMBERS)
    back = reverse("members", args=[clinic.pk])
    role = _role(request)
    if role is None:
        return _refused(request, "choose a role", 400, back)
    with transaction.atomic():
        member = get_object_or_404(clinic.members.select_related("user"), pk=member_id)
        if not _keeps_an_administrator(clinic, member, role):
            return _refused(request, "the clinic must keep at least one administrator", 409, back)
        member.role = role
        member.save(update_fields=["role"])
    messages.success(request, f"{member.user.username} is now {role}.")
    return redirect(back)


@login_required
@require_POST
def remove_member(request, clinic_id, member_id):
    clinic = _require_role(request, clinic_id, MANAGE_MEMBERS)
    back = reverse("members", args=[clinic.pk])
    with transaction.atomic():
        member = get_object_or_404(clinic.members.select_related("user"), pk=member_id)
        if not _keeps_an_administrator(clinic, member):
            return _refused(request, "the clinic must keep at least one administrator", 409, back)
        member.delete()
    messages.success(request, f"{member.user.username} removed from {clinic.name}.")
    return redirect(back if member.user != request.user else "patients")
