"""The clinicians' pages: patients, a patient's history, a visit, a comparison, a rig.

Every query goes through ``clinics_of(request.user)``: anything outside the
user's clinics is a 404 (a patient's scans are the patient's clinic's, wherever
the rig has gone since: ``captures_of``). What a member may change depends on
their role, and the pages ask the API's rule (below), so a page never allows
what the API forbids, with one exception: every member who may see a
comparison may have a failed one computed again ("Try again"; it is derived
from two stored scans and discards nothing). Pages are plain HTML (a running
job's page refreshes itself with a meta tag, no JavaScript needed).
"""

import functools
import hashlib
import io
import json
import logging
import math
import tempfile
import uuid
from pathlib import Path

from django import forms
from django.conf import settings
from django.contrib import messages
from django.contrib.auth import get_user_model
from django.contrib.auth.decorators import login_required
from django.core import validators
from django.core.exceptions import BadRequest, PermissionDenied
from django.core.files.storage import default_storage
from django.db import IntegrityError, connection, transaction
from django.core.cache import cache
from django.core.paginator import Paginator
from django.db.models import Count, Exists, F, Max, OuterRef, Q
from django.core.files.base import ContentFile
from django.http import FileResponse, Http404, HttpResponse, JsonResponse
from django.shortcuts import get_object_or_404, redirect, render
from django.urls import reverse
from django.utils import timezone
from django.views.decorators.http import require_http_methods, require_POST

from . import api, labels, once, pipeline
from .models import (CaptureSession, Comparison, Job, Member, Patient, Reconstruction, Rig, StabilityCheck, Visit,
                     captures_of, clinics_of, jobs_of)
from .validation import MAX_NOTES, Invalid, check_param

# Who may do what. Actions the API has (re-running a job, issuing and revoking a rig's keys) are run through
# the API's own operations, so the pages get its scoping, its role check (`member_clinic`, administrators and
# technicians) and its logic. Actions only the pages have ask the same helper with these roles:
CORRECT_LANDMARKS = (Member.CLINICIAN, Member.ADMINISTRATOR)  # a clinical judgement: not technicians
MANAGE_MEMBERS = (Member.ADMINISTRATOR,)
EDIT_PATIENTS = (Member.CLINICIAN, Member.TECHNICIAN, Member.ADMINISTRATOR)  # as the API's create_patient
LANDMARK_LIMIT_MM = 5000.0  # a landmark's coordinates in the rig's frame: the rig is a couple of metres across

log = logging.getLogger(__name__)


def _require_role(request, clinic_id, roles=None):
    """The clinic, if the user's role in it allows the action: 404 for a non-member, 403 for another role."""
    try:
        if roles is None:  # the API's default: what its staff endpoints allow
            return api.member_clinic(request, clinic_id)
        return api.member_clinic(request, clinic_id, roles=roles)
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
    except Invalid as exc:  # a field of the address or the form breaks a rule: the page says which
        raise BadRequest(str(exc)) from None
    return json.loads(out.content) if isinstance(out, HttpResponse) else out


def _refused(request, message, status, back=None):
    return render(request, "clinic/error.html", {"message": message, "back": back}, status=status)


def bad_request(request, exception=None):
    """A refused request: ours (``BadRequest``, raised by :func:`_run_api`) with what was wrong in it; Django's
    own (a forged Host header, its other ``SuspiciousOperation`` refusals) without their words, which name
    settings."""
    words = str(exception) if type(exception) is BadRequest else ""
    return _refused(request, words or "The request could not be understood.", 400)


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


def _flat(indices):
    from analysis.repeatability import flatten

    return flatten(indices or {})


def _patients(user):
    return Patient.objects.filter(clinic__in=clinics_of(user))


def _reconstructions(user):
    return Reconstruction.objects.filter(captures_of(clinics_of(user), "session"))


def _good_recs():
    return Reconstruction.objects.filter(status__in=["ok", "partial"], job__state=Job.SUCCEEDED)


def best_scan(visit):
    """The visit's torso shown to clinicians: its latest good reconstruction (or None)."""
    return _good_recs().filter(session__visit=visit).order_by("-created").first()


def _scan_jobs(visit):
    """The jobs that made the visit's scans (the comparisons it is in are the comparison page's)."""
    return Job.objects.filter(session__visit=visit).exclude(kind=Job.COMPARISON).order_by("-created")


def scans_of(patient) -> list:
    """Every good reconstruction of the patient in time order, each with a label a clinician can choose by."""
    recs = list(_good_recs().filter(session__visit__patient=patient).select_related("session__visit")
                .order_by("session__visit__date", "session__visit_id", "created", "pk"))
    per_visit = {}
    for r in recs:
        per_visit.setdefault(r.session.visit_id, []).append(r)
    for r in recs:
        same = per_visit[r.session.visit_id]
        k = same.index(r) + 1
        r.scan_label = (f"{r.session.visit.date} · scan {k} of {len(same)}" if len(same) > 1
                        else f"{r.session.visit.date}") + (f" · {r.session.visit.reason}" if r.session.visit.reason else "")
    return recs


def best_of_visits(scans) -> dict:
    """Each visit's torso shown to clinicians (as :func:`best_scan`: its latest good reconstruction), from the
    patient's :func:`scans_of`, by visit id: one query for a whole history."""
    best = {}
    for r in scans:  # in time order within each visit
        cur = best.get(r.session.visit_id)
        if cur is None or (r.created, r.pk) > (cur.created, cur.pk):
            best[r.session.visit_id] = r
    return best


def _last_scan_jobs(p) -> dict:
    """Each visit's latest scan job (as ``_scan_jobs(visit).first()``), by visit id: one query."""
    last = {}
    for job in (Job.objects.filter(session__visit__patient=p).exclude(kind=Job.COMPARISON)
                .annotate(visit_pk=F("session__visit_id")).order_by("-created")):
        last.setdefault(job.visit_pk, job)
    return last


# The clinic's MDC and repeat-pair count rest on every repeat pair of its rigs: reading them all on each page
# grows with the clinic's history, so each is kept in the cache under the state of those pairs (one aggregate
# query on the repeat pairs' index): a repeat pair added or removed (a landmark correction removes the
# comparisons of its torso) is a new key. Computed, on a miss, by analysis_step's own functions, made to read the
# repeat pairs only (not every comparison of the clinic: at 10 000 patients, gigabytes of reports).
MDC_CACHE_SECONDS = 24 * 3600


def _repeat_state(clinic) -> str:
    """A key of the clinic's repeat pairs (same-visit comparisons) as they stand; asked once per clinic object
    (a request's: the MDC and the noise of one page rest on the same pairs)."""
    key = getattr(clinic, "_repeat_state_key", None)
    if key is None:
        state = _repeat_comparisons(clinic).aggregate(n=Count("pk"), last=Max("pk"), newest=Max("created"))
        newest = state["newest"].timestamp() if state["newest"] else None
        key = f"{clinic.pk}:{clinic.created.timestamp()}:{state['n']}:{state['last']}:{newest}"
        clinic._repeat_state_key = key
    return key


@functools.cache
@functools.lru_cache(maxsize=16)
def files_digest(paths: tuple, salt: str = "") -> str:
    """A short digest of ``salt`` and the bytes of ``paths`` (a missing file counts as "-"): part of a cache key, so
    that a cache shared by the processes of two releases (CACHE_URL) never serves what the older code computed.
    Read once per process: a release is a new process."""
    digest = hashlib.sha256(salt.encode())
    for path in paths:
        digest.update(Path(path).read_bytes() if Path(path).exists() else b"-")
    return digest.hexdigest()[:16]


def _mdc_code_state() -> str:
    """The scanner's repeatability and the code that turns pairs into MDCs."""
    from analysis import repeatability

    from . import analysis_step

    return files_digest((repeatability.__file__, analysis_step.__file__,
                         str(Path(repeatability.__file__).with_name("scanner_mdc.json"))))


def _cached_by_repeat_state(what, clinic, compute):
    # the clinic's cameras pick the scanner's MDC set (analysis_step.clinic_mdc); rigs change rarely, and the entry
    # lives MDC_CACHE_SECONDS
    key = f"torsoscan:{what}:{_mdc_code_state()}:{_repeat_state(clinic)}"
    value = cache.get(key)
    if value is None:
        value = compute(clinic)
        cache.set(key, value, MDC_CACHE_SECONDS)
    return value


def _repeat_comparisons(clinic):
    """The clinic's repeat pairs (two scans of one visit, marked so when stored), chosen by the database."""
    return Comparison.objects.filter(repeat=True, later__session__rig__clinic=clinic)


def cached_mdc(clinic):
    from . import analysis_step

    return _cached_by_repeat_state("mdc", clinic, analysis_step.clinic_mdc)


def noise_state(clinic) -> dict:
    """What the noise verdicts rest on: the clinic's repeat pairs and how many are needed before any flag."""
    from analysis.repeatability import MIN_REPEAT_PAIRS

    from . import analysis_step

    pairs = _cached_by_repeat_state("repeat-pairs", clinic, analysis_step.repeat_pairs)
    return {"pairs": pairs, "needed": MIN_REPEAT_PAIRS, "ready": pairs >= MIN_REPEAT_PAIRS}


# --- words for a clinician ------------------------------------------------------------------

def _age(born, on) -> str | None:
    """Age in years and months on a date ("12 y 4 mo"), or None without a date of birth."""
    if not born or not on:
        return None
    months = (on.year - born.year) * 12 + on.month - born.month - (on.day < born.day)
    if months < 0:
        return None
    return f"{months // 12} y {months % 12} mo"


def span_words(earlier, later) -> str:
    """The time between two dates in words."""
    days = (later - earlier).days
    if days <= 0:
        return "the same day"
    if days < 60:
        return f"{days} day{'s' if days != 1 else ''}"
    months = round(days / 30.44)
    if months < 24:
        return f"{months} months"
    return f"{months / 12:.1f} years"


def patient_context(p, on=None) -> dict:
    """What names the patient on every page: name, identifier, date of birth, age (now and on ``on``)."""
    from django.utils import timezone

    return {"patient": p, "age_now": _age(p.date_of_birth, timezone.localdate()),
            "age_then": _age(p.date_of_birth, on) if on else None, "age_on": on}


def not_measurable_of(rec, when: str) -> dict | None:
    nm = (rec.indices or {}).get("not_measurable") if rec else None
    if not nm:
        return None
    mark = [labels.landmark(m) for m in nm.get("mark") or []]
    facing = (((rec.indices or {}).get("frame") or {}).get("facing") or {}).get("status") == "uncertain"
    if facing and not mark:
        mark = [labels.landmark("vertebra_prominens")]
    names = {labels.label(k) for k in _flat_keys_of(nm.get("indices") or [])}
    reason = nm.get("reason", "")
    for prefix in ("not measurable on this scan: ", "not measurable on this scan; "):
        reason = reason[len(prefix):] if reason.startswith(prefix) else reason
    return {"when": when, "visit_id": rec.session.visit_id, "reason": reason,
            "mark": mark, "indices": sorted(names)}


def _flat_keys_of(bases) -> list:
    """The labelled keys resting on the report's top-level figures ``bases``."""
    return [k for k in labels.TABLE_KEYS if k.split(".")[0] in bases]


def verdict_of(clinic, earlier, later, title, mdc=None, noise=None, sides_agree=None, growth=None) -> dict:
    """The headline of two scans: what changed beyond the scanner's noise (by how much, where), what stayed
    within it, what cannot be judged yet and why (``no_verdict``: a landmark placed two ways), what is not
    measurable, and growth apart."""
    from analysis.repeatability import index_changes

    mdc = cached_mdc(clinic) if mdc is None else mdc
    noise = noise_state(clinic) if noise is None else noise
    comp = Comparison.objects.filter(earlier=earlier, later=later).first()
    if sides_agree is None:
        sides_agree = ((comp.report.get("facing") or {}).get("consistent", True)) if comp else True
    if growth is None and comp:
        growth = comp.report.get("growth")
    changes = index_changes(earlier.indices or {}, later.indices or {}, mdc, sides_agree=sides_agree)
    out = {"title": title, "earlier": earlier, "later": later,
           "earlier_date": earlier.session.visit.date, "later_date": later.session.visit.date,
           "span": span_words(earlier.session.visit.date, later.session.visit.date),
           "repeat": earlier.session.visit_id == later.session.visit_id, "noise": noise,
           "beyond": [], "within": [], "unjudged": [], "no_verdict": [], "growth": [], "sides_agree": sides_agree,
           "not_measurable": [x for x in (not_measurable_of(earlier, f"the scan of {earlier.session.visit.date}"),
                                          not_measurable_of(later, f"the scan of {later.session.visit.date}")) if x]}
    for key in labels.HEADLINE_KEYS + labels.GROWTH_KEYS:
        c = changes.get(key)
        if c is None:
            continue
        ix = labels.index(key)
        words = labels.change_texts(key, c)
        item = {"label": ix.label, "meaning": ix.meaning, "unit": ix.unit,
                "change": words["change"],
                "size": abs(c["change"]),
                "from_to": words["from_to"], "was": words["earlier"], "now": words["later"],
                "mdc": None if c["mdc"] is None else f"± {c['mdc']:.1f}{'' if ix.unit == '°' else ' '}{ix.unit}",
                "where": "; ".join(s["words"] for s in labels.sides(later.indices, key))}
        if ix.growth:
            out["growth"].append(item)
        elif c.get("no_verdict"):
            out["no_verdict"].append({**item, "reason": c["no_verdict"].removeprefix("no verdict: ")})
        elif c["exceeds_mdc"] is True:
            out["beyond"].append(item)
        elif c["exceeds_mdc"] is False:
            out["within"].append(item)
        else:
            out["unjudged"].append(item)
    # a verdict may rest on an MDC the clinic did not measure itself (the scanner's own, while the clinic has
    # too few repeat pairs): say so rather than "no verdict possible"
    out["judged"] = bool(out["beyond"] or out["within"])
    out["scanner_mdc"] = any((m or {}).get("source") == "scanner" for m in mdc.values())
    out["unjudged"].sort(key=lambda x: -x["size"] if x["unit"] == "mm" else -3 * x["size"])
    for key, name in labels.GROWTH_FIGURES[1:]:
        ch = ((growth or {}).get("change") or {}).get(key)
        if ch is not None:
            out["growth"].append({"label": name, "change": f"{ch:+.1f} mm",
                                  "from_to": f"{growth['earlier'][key]:.1f} mm → {growth['later'][key]:.1f} mm"})
    return out


def headline_of(p, scans_by_visit, mdc, noise) -> list:
    """Since the baseline and since the last visit, for the patient's latest scan."""
    recs = [r for r in scans_by_visit if r is not None]
    if len(recs) < 2:
        return []
    base, prev, latest = recs[0], recs[-2], recs[-1]
    out = [verdict_of(p.clinic, base, latest, "Since the baseline", mdc, noise)]
    if prev != base:
        out.append(verdict_of(p.clinic, prev, latest, "Since the last visit", mdc, noise))
    return out


# thresholds of the scan-quality verdict: (good up to, usable up to); beyond: repeat the scan
PAIR_DISTANCE_MM = (0.5, 1.0)  # average normal distance between neighbouring arms after registration
OVERLAP_MATCHED = (0.9, 0.6)  # share of each overlap that registered (at least)


def scan_quality(rec) -> dict:
    """One verdict on a scan, in words: good, usable or repeat the scan, and why."""
    if rec is None:
        return {"verdict": "none", "words": "No torso yet", "reasons": []}
    report = rec.report or {}
    reasons, level = [], 0  # 0 good, 1 usable, 2 repeat

    def worse(k, why):
        nonlocal level
        level = max(level, k)
        reasons.append(why)

    if rec.status == "failed":
        worse(2, "the reconstruction failed")
    elif rec.status == "partial":
        worse(1, "part of the torso is missing (an arm of the rig gave no surface)")
    for prob in report.get("problems") or []:
        worse(1, str(prob))
    pairs = (report.get("registration") or {}).get("pairs") or []
    for pair in pairs:
        d, m = pair.get("average_normal_distance_mm"), pair.get("overlap_matched_fraction")
        name = f"arms {pair.get('a')} and {pair.get('b')}"
        if d is not None and d > PAIR_DISTANCE_MM[1]:
            worse(2, f"{name} fit together only to {d:.2f} mm (the patient may have moved)")
        elif d is not None and d > PAIR_DISTANCE_MM[0]:
            worse(1, f"{name} fit together to {d:.2f} mm only")
        if m is not None and m < OVERLAP_MATCHED[1]:
            worse(2, f"only {100 * m:.0f} % of the overlap of {name} matched")
        elif m is not None and m < OVERLAP_MATCHED[0]:
            worse(1, f"{100 * m:.0f} % of the overlap of {name} matched")
    from analysis.indices import CORE_LANDMARKS

    ind = rec.indices or {}
    for name, lm in (ind.get("landmarks") or {}).items():
        if name not in CORE_LANDMARKS:
            continue  # the dimples are the body's, not the scan's: only the pelvic figures wait for them
        conf = lm.get("confidence")
        if conf not in (None, "high", "clinician"):
            worse(1, f"the {labels.landmark(name)} was placed with {conf} confidence: check it or mark it")
    facing = ((ind.get("frame") or {}).get("facing") or {})
    if facing.get("status") == "uncertain":
        worse(1, "the patient's facing is uncertain, so left and right cannot be told: mark C7 on the back")
    if rec.indices is None:
        worse(1, "the indices are not computed yet")
    words = ("Good scan", "Usable scan, with reservations", "Repeat the scan")[level]
    return {"verdict": ("good", "usable", "repeat")[level], "words": words, "reasons": reasons}


def index_rows_of(indices) -> list:
    """The visit page's indices: label, value with its side in words, where it is largest, meaning."""
    flat = _flat(indices)
    withheld = set(((indices or {}).get("not_measurable") or {}).get("indices") or [])
    rows = []
    for key in labels.TABLE_KEYS:
        ix = labels.index(key)
        v = flat.get(key)
        rows.append({"label": ix.label, "unit": ix.unit, "meaning": ix.meaning, "growth": ix.growth,
                     "value": labels.size_words(key, v) if v is not None else None,
                     "not_measurable": v is None and key.split(".")[0] in withheld,
                     # an RMS is largest where its maximum is: said once, on the maximum's row
                     "where": [s["words"] for s in labels.sides(indices, key)]
                     if v is not None and not key.endswith(".rms") else []})
    return rows


def _pictures(kind, obj) -> list:
    return [{"name": name, "title": labels.picture(name)[0], "alt": labels.picture(name)[1],
             "src": reverse("picture", args=[kind, obj.pk, name]),
             "page": reverse("picture_page", args=[kind, obj.pk, name])} for name in (obj.pictures or {})]


WORKLIST_LIMIT = 50  # overdue patients listed on the home page, the longest overdue first
PATIENTS_PER_PAGE = 50  # the patient list (and a search's results), by name, a page at a time


def months_before(day, months):
    """The same day of the month ``months`` earlier (the month's last day where it is shorter)."""
    import calendar

    y, m = divmod(day.year * 12 + day.month - 1 - months, 12)
    return day.replace(year=y, month=m + 1, day=min(day.day, calendar.monthrange(y, m + 1)[1]))


def _worklist(user, today) -> dict:
    """Today's visits and the patients whose follow-up is overdue, in the user's clinics.

    Overdue: the next visit due date set at the patient's latest visit has passed; where none was set, the
    latest visit is more than ``FOLLOW_UP_MONTHS`` old. A patient with a visit booked from today on is not
    overdue (the latest visit is that one)."""
    from django.db.models import Subquery

    months = getattr(settings, "FOLLOW_UP_MONTHS", 6)
    visits_today = (Visit.objects.filter(patient__in=_patients(user), date=today)
                    .select_related("patient", "patient__clinic").order_by("patient__name", "id")
                    .annotate(scanned=Exists(CaptureSession.objects.filter(visit=OuterRef("pk")))))
    # each patient's latest visit: index lookups (visit_latest_per_patient)
    latest = Visit.objects.filter(patient=OuterRef("pk")).order_by("-date", "-id")
    cutoff = months_before(today, months)
    overdue = []
    for row in (_patients(user).annotate(last_visit=Subquery(latest.values("date")[:1]),
                                         due=Subquery(latest.values("next_visit_due")[:1]))
                .filter(Q(due__lt=today) | Q(due__isnull=True, last_visit__lt=cutoff))
                .values("pk", "name", "identifier", "last_visit", "due")):
        row["due_since"] = row["due"] or months_before(row["last_visit"], -months)
        overdue.append(row)
    overdue.sort(key=lambda r: (r["due_since"], r["name"]))
    for row in overdue[:WORKLIST_LIMIT]:
        row["late"] = span_words(row["due_since"], today)
    return {"today": today, "visits_today": visits_today, "overdue": overdue[:WORKLIST_LIMIT],
            "overdue_count": len(overdue), "follow_up_months": months}



@login_required
def patients(request):
    """The worklist (today's visits, overdue follow-ups), then the patients of the user's clinics, with a
    search by name or identifier."""
    q = request.GET.get("q", "").strip()
    rows = _patients(request.user).select_related("clinic").order_by("name", "pk")
    if q:
        rows = rows.filter(Q(name__icontains=q) | Q(identifier__icontains=q))
    page = Paginator(rows, PATIENTS_PER_PAGE).get_page(request.GET.get("page"))
    visits = dict(Visit.objects.filter(patient__in=[p.pk for p in page]).values("patient")
                  .annotate(n=Count("pk")).values_list("patient", "n"))
    for p in page:
        p.visit_count = visits.get(p.pk, 0)
    rigs = Rig.objects.filter(clinic__in=clinics_of(request.user))
    administered = [c for c in clinics_of(request.user) if _may(request, c.pk, MANAGE_MEMBERS)]
    return render(request, "clinic/patients.html", {"patients": page, "page": page, "q": q, "rigs": rigs,
                                                    "administered": administered,
                                                    # a search shows the matching patients only
                                                    "worklist": None if q else _worklist(request.user,
                                                                                         timezone.localdate()),
                                                    "may_edit": any(_may(request, c.pk, EDIT_PATIENTS)
                                                                    for c in clinics_of(request.user))})


@login_required
def patient(request, patient_id):
    """A patient's history: the headline (what changed beyond noise), visits, index trends, the latest pictures."""
    p = get_object_or_404(_patients(request.user).select_related("clinic"), pk=patient_id)
    scans = scans_of(p)
    best, last_jobs = best_of_visits(scans), _last_scan_jobs(p)
    visits = []
    for v in p.visits.all():
        rec = best.get(v.pk)
        visits.append({"visit": v, "rec": rec, "job": last_jobs.get(v.pk), "flat": _flat(rec.indices if rec else None),
                       "age": _age(p.date_of_birth, v.date), "quality": scan_quality(rec) if rec else None,
                       "scans": sum(1 for s in scans if s.session.visit_id == v.pk)})
    mdc = cached_mdc(p.clinic)
    noise = noise_state(p.clinic)
    rows = []
    for key in labels.TABLE_KEYS:
        ix = labels.index(key)
        vals = [x["flat"].get(key) for x in visits]
        m = (mdc.get(key) or {}).get("mdc")
        first = next((v for v in vals if v is not None), None)
        rows.append({"label": ix.label, "unit": ix.unit, "meaning": ix.meaning, "mdc": m, "growth": ix.growth,
                     "cells": [{"value": v, "beyond": (not ix.growth and v is not None and first is not None
                                                       and m is not None and abs(v - first) > m)} for v in vals]})
    latest = next((x["rec"] for x in reversed(visits) if x["rec"]), None)
    headline = headline_of(p, [x["rec"] for x in visits], mdc, noise)
    return render(request, "clinic/patient.html", {
        **patient_context(p), "visits": visits, "rows": rows, "latest": latest, "scans": scans,
        "noise": noise, "headline": headline,
        "latest_pictures": _pictures("reconstruction", latest) if latest else [],
        "earlier_default": scans[0].pk if scans else None, "later_default": latest.pk if latest else None,
        "may_edit": _may(request, p.clinic_id, EDIT_PATIENTS)})


def _trend_name(p, series, mdc) -> str:
    """Where the trend picture of these scans and this MDC state is kept (a new state, a new name)."""
    import hashlib

    state = json.dumps([[str(d), pk, ind] for d, pk, ind in series] + [mdc], sort_keys=True, default=str)
    return f"trends/patient-{p.pk}/{hashlib.sha256(state.encode()).hexdigest()[:24]}.png"


@login_required
def patient_trend(request, patient_id):
    """The trend plot of every index over the patient's visits (PNG): drawn once per state of the scans and
    MDC, then served from storage."""
    from analysis import pictures

    p = get_object_or_404(_patients(request.user).select_related("clinic"), pk=patient_id)
    best = best_of_visits(scans_of(p))
    series = [(v.date, rec.pk, rec.indices) for v in p.visits.all() if (rec := best.get(v.pk)) and rec.indices]
    if not series:
        raise Http404("no visit with a torso yet")
    mdc = {k: v["mdc"] for k, v in cached_mdc(p.clinic).items()}
    name = _trend_name(p, series, mdc)
    if default_storage.exists(name):
        return FileResponse(default_storage.open(name, "rb"), content_type="image/png")
    figures = [(k, labels.label(k) + (f" ({labels.unit(k)})" if labels.unit(k) else ""))
               for k, _ in pictures.TREND_FIGURES]
    with tempfile.TemporaryDirectory() as tmp:
        png = pictures.trend_picture([(str(d), ind) for d, _, ind in series], Path(tmp) / "trend.png", mdc=mdc,
                                     figures=figures)
        data = Path(png).read_bytes()
    _store_replacing_older_states(name, data)
    return HttpResponse(data, content_type="image/png")


def _store_replacing_older_states(name: str, data: bytes) -> None:
    """Store a drawing under ``name`` (its folder holds one patient's or rig's drawings, one file per state of
    what it plots) and delete that folder's drawings of older states: only the latest state is ever asked for."""
    try:
        folder = str(Path(name).parent)
        for old in default_storage.listdir(folder)[1]:
            default_storage.delete(f"{folder}/{old}")
    except (OSError, NotImplementedError):
        pass
    default_storage.save(name, ContentFile(data))


@login_required
def visit(request, visit_id):
    """A visit: its verdict on the scan's quality, torso pictures, indices in words; technical details folded."""
    v = get_object_or_404(Visit.objects.filter(patient__clinic__in=clinics_of(request.user)), pk=visit_id)
    rec = best_scan(v)
    jobs = list(_scan_jobs(v))
    running = any(j.state in (Job.QUEUED, Job.RUNNING) for j in jobs)
    report = rec.report if rec else {}
    pairs = report.get("registration", {}).get("pairs", [])
    arms = {a: {"points": r.get("points"), "sigma": r.get("sigma_mm_median")} for a, r in report.get("arms", {}).items()}
    scans = [s for s in scans_of(v.patient) if s.session.visit_id == v.pk]
    landmark_job = pipeline.landmark_job_of(rec) if rec else None
    recomputing = landmark_job is not None and landmark_job.state in (Job.QUEUED, Job.RUNNING)
    return render(request, "clinic/visit.html", {
        **patient_context(v.patient, v.date),
        "visit": v, "rec": rec, "jobs": jobs, "running": running or recomputing, "pairs": pairs, "arms": arms,
        "landmark_job": landmark_job, "recomputing": recomputing,
        "landmark_version": landmark_version(rec) if rec else "",
        "pick_src": reverse("picture", args=["reconstruction", rec.pk, f"torso-{PICK_VIEW}"])
        if rec and f"torso-{PICK_VIEW}" in (rec.pictures or {}) and (rec.indices or {}).get("frame") else None,
        "quality": scan_quality(rec), "index_rows": index_rows_of(rec.indices if rec else None),
        "not_measurable": not_measurable_of(rec, "this scan") if rec else None,
        "pictures": _pictures("reconstruction", rec) if rec else [], "scans": scans,
        "landmarks": (rec.indices or {}).get("landmarks", {}) if rec else {},
        "may_rerun": _may(request, v.patient.clinic_id),
        "may_correct": _may(request, v.patient.clinic_id, CORRECT_LANDMARKS),
        "may_edit": _may(request, v.patient.clinic_id, EDIT_PATIENTS)})


@login_required
@require_POST
def correct_landmarks(request, visit_id):
    """A clinician moves the vertebra prominens, the sacral point or a lumbar dimple; the indices, pictures and
    comparisons resting on them are computed again; who changed what is kept for undo."""
    v, rec = _torso_to_correct(request, visit_id)
    if rec is None:
        raise Http404("this visit has no torso yet")
    landmarks = {}  # every landmark is checked before any is stored
    from analysis.indices import LANDMARKS

    for name in LANDMARKS:
        raw = request.POST.get(name, "").strip()
        if raw:
            try:
                xyz = [float(t) for t in raw[:200].replace(",", " ").split()]
            except ValueError:
                xyz = []
            # finite and within a few metres of the rig: NaN or 1e300 would break the indices (and JSON)
            if len(xyz) != 3 or not all(math.isfinite(c) and abs(c) <= LANDMARK_LIMIT_MM for c in xyz):
                return _refused(request, f"{name.replace('_', ' ')}: give three numbers x y z in mm (each within "
                                         f"±{LANDMARK_LIMIT_MM:g} mm), got {raw[:80]!r}", 400,
                                back=reverse("visit", args=[v.pk]) + "#landmarks")
            landmarks[name] = xyz
    return _apply_landmarks(request, v, rec, lambda cur: (landmarks or None, _history_after(request, cur)))


LANDMARK_HISTORY = 20  # corrections a torso keeps for undo


def _torso_to_correct(request, visit_id):
    """``(visit, its best torso or None)`` for a landmark correction: 404 outside the user's clinics, 403 for a
    role that may not correct landmarks."""
    v = get_object_or_404(Visit.objects.filter(patient__clinic__in=clinics_of(request.user)), pk=visit_id)
    _require_role(request, v.patient.clinic_id, CORRECT_LANDMARKS)
    return v, best_scan(v)


def _history_after(request, rec) -> list:
    """The torso's correction history with the landmarks a correction now replaces (who, when), for undo."""
    entry = {"landmarks": rec.landmarks, "by": request.user.get_username(),
             "at": timezone.now().isoformat(timespec="seconds")}
    return [*(rec.landmark_history or []), entry][-LANDMARK_HISTORY:]


def _short_hash(value, digits: int) -> str:
    """The first ``digits`` hex digits of the SHA-256 of ``value`` as JSON (keys sorted, dates as text)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()[:digits]


def landmark_version(rec) -> str:
    """What a landmark form was drawn from: the torso, its landmarks and their history, and the patient frame
    its pictures were drawn in (a click is read through it). A correction posted with another torso's, after
    someone else's correction or undo, or from pictures drawn before the indices were computed again, is refused
    rather than applied over it."""
    return f"{rec.pk}-{_short_hash([rec.landmarks, rec.landmark_history, (rec.indices or {}).get('frame')], 16)}"


@login_required
@require_POST
def undo_landmarks(request, visit_id):
    """The last landmark correction undone: the landmarks before it come back, and everything is computed again."""
    v, rec = _torso_to_correct(request, visit_id)
    if rec is None:
        raise Http404("no landmark correction to undo")

    def undone(cur):
        # judged on the locked row, after the page's version: an undo from a page drawn before another undo is
        # a conflict (409), one with nothing to undo from a current page (or without a page) a 404
        history = list(cur.landmark_history or [])
        if not history:
            raise Http404("no landmark correction to undo")
        return history.pop().get("landmarks"), history

    return _apply_landmarks(request, v, rec, undone)


class _LandmarksChanged(Exception):
    """The torso's landmarks are not those the correction was made on."""


def _apply_landmarks(request, v, rec, change):
    """Store the landmarks ``change(torso)`` gives (with who changed what, for undo), then compute the torso's
    indices and pictures again as a job (the visit page shows its progress; in the embedded default it runs
    here); the comparisons resting on the torso are queued again by it. If the indices cannot be computed from
    these landmarks, the job puts the previous ones back and says so on the visit page.

    The torso's row is locked and read again first, so two corrections at once apply one after the other, each
    to the landmarks the other left; one posted from a page drawn before another correction (its
    ``based_on`` is not :func:`landmark_version`) is refused with 409 and stores nothing."""
    based_on = request.POST.get("based_on")
    try:
        with transaction.atomic():
            cur = Reconstruction.objects.select_for_update().get(pk=rec.pk)
            if based_on is not None and based_on != landmark_version(cur):
                raise _LandmarksChanged()
            cur.landmarks, cur.landmark_history = change(cur)
            cur.save(update_fields=["landmarks", "landmark_history"])
            job = pipeline.queue_landmark_analysis(cur)  # committed with the landmarks
    except _LandmarksChanged:
        # who is not named: an undo leaves no entry, so the history's last author may be someone before the page
        return _refused(request, "This scan's landmarks changed since this page was opened (another correction, "
                                 "an undo, or the indices computed again), or a newer scan of the visit came: "
                                 "nothing was stored. Look at the page again (its history says who corrected "
                                 "what), then correct what is still wrong.", 409, back=reverse("visit", args=[v.pk]))
    job = pipeline.send_now(job)
    if job.state == Job.SUCCEEDED:
        messages.info(request, "The indices and pictures were computed again from the corrected landmarks; the "
                               "comparisons with this scan are being computed again.")
    elif job.state != Job.FAILED:
        messages.info(request, "The indices and pictures are being computed again from the corrected landmarks.")
    return redirect("visit", visit_id=v.pk)


PICK_VIEW = "back"  # the picture a landmark is placed on (torso_views' back view, its default size)


@login_required
@require_POST
def pick_landmark(request, visit_id):
    """A landmark placed by clicking on the back picture: the skin point drawn under the click becomes it."""
    from analysis.frame import PatientFrame
    from analysis.indices import LANDMARKS
    from analysis.pictures import pick_point

    from .analysis_step import local_copy, stored

    v, rec = _torso_to_correct(request, visit_id)
    if rec is None or not (rec.indices or {}).get("frame"):
        raise Http404("this visit has no analysed torso yet")
    back = reverse("visit", args=[v.pk]) + "#pick"
    name = request.POST.get("landmark", "")
    if name not in LANDMARKS:
        return _refused(request, f"landmark: choose one of {', '.join(n.replace('_', ' ') for n in LANDMARKS)} "
                                 f"before clicking (got {name[:40]!r})", 400, back=back)
    try:
        x, y = float(request.POST["at.x"]), float(request.POST["at.y"])
    except (KeyError, ValueError):
        return _refused(request, "at: click on the back picture to place the landmark (no position was sent)",
                        400, back=back)
    if not (math.isfinite(x) and math.isfinite(y)):
        return _refused(request, "at: the position clicked is not a number", 400, back=back)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        mesh = local_copy(rec.mesh, tmp / "torso-mesh.ply") if stored(rec.mesh) else None
        point = pick_point(local_copy(rec.torso, tmp / "torso.ply"), PatientFrame.from_dict(rec.indices["frame"]),
                           PICK_VIEW, x, y, mesh=mesh)
    if point is None:
        return _refused(request, f"at: there is no skin at ({x:.0f}, {y:.0f}) on the picture; click on the back",
                        400, back=back)
    placed = [round(float(c), 1) for c in point]
    return _apply_landmarks(request, v, rec,
                            lambda cur: ({**(cur.landmarks or {}), name: placed}, _history_after(request, cur)))


@login_required
@require_http_methods(["GET", "HEAD", "POST"])
def comparison(request, patient_id):
    """Any two scans of the patient (two visits, or a same-day re-scan): the verdict, then the deformation map,
    per-region changes and every index's change against the scanner's noise.

    A pair not compared yet is compared by a job (registering two torsos takes a while), started by a POST (the
    patient page's form, the page's own button): a GET only shows what there is, so a followed link, a prefetch
    or a reload starts nothing. The page shows the job's progress and refreshes itself until the result is there.
    A failed job can be tried again (POST)."""
    p = get_object_or_404(_patients(request.user), pk=patient_id)
    back = reverse("patient", args=[p.pk])
    scans = scans_of(p)
    order = {r.pk: k for k, r in enumerate(scans)}
    by_pk = {r.pk: r for r in scans}
    # a form's POST carries its choice in the body; the page's own buttons post to its address (the query)
    asked = request.POST if "earlier_scan" in request.POST or "earlier" in request.POST else request.GET
    if not any(f in asked for f in ("earlier_scan", "later_scan", "earlier", "later")):
        # no pair: e.g. back from signing in after a form posted once the session had ended (the sign-in keeps
        # the address, not the form): the patient's page, where the pair is chosen
        return redirect(back)
    try:
        if "earlier_scan" in asked or "later_scan" in asked:
            earlier, later = (by_pk.get(int(asked.get(f, ""))) for f in ("earlier_scan", "later_scan"))
            if earlier is None or later is None:
                raise Http404("no such scan of this patient")
        else:  # two visits: each one's scan shown to clinicians; one visit twice: its first scan and its latest
            earlier_v = get_object_or_404(p.visits, pk=int(asked.get("earlier", "")))
            later_v = get_object_or_404(p.visits, pk=int(asked.get("later", "")))
            if earlier_v == later_v:
                same = [r for r in scans if r.session.visit_id == earlier_v.pk]
                earlier, later = (same[0], same[-1]) if same else (None, None)
            else:
                earlier, later = best_scan(earlier_v), best_scan(later_v)
            if earlier is None or later is None:
                return _refused(request, "Both visits need a reconstructed torso to be compared.", 404, back)
            earlier, later = by_pk.get(earlier.pk), by_pk.get(later.pk)
    except ValueError:
        raise Http404("choose two scans") from None
    if earlier == later:
        return _refused(request, "Choose two different scans: this visit has one scan only, and a scan compared "
                                 "with itself shows nothing. A same-day re-scan can be compared once it exists.",
                        400, back)
    if order[later.pk] < order[earlier.pk]:
        earlier, later = later, earlier
    comp = Comparison.objects.filter(earlier=earlier, later=later).first()
    if request.method == "POST":
        if comp is None:
            _comparison_job(earlier, later)
        # to the pair's own address, so that the page's refresh (and a reload) does not post again
        return redirect(f"{reverse('comparison', args=[p.pk])}?earlier_scan={earlier.pk}&later_scan={later.pk}")
    if comp is None:
        job = pipeline.comparison_job_of(earlier, later)
        if job is not None and job.state == Job.SUCCEEDED:  # finished since the first read, or its result removed
            comp = Comparison.objects.filter(earlier=earlier, later=later).first()
            job = None  # (removed: the page offers to compare again)
    if comp is None:
        return render(request, "clinic/comparison_progress.html", {
            **patient_context(p), "job": job, "earlier": earlier, "later": later,
            "repeat": earlier.session.visit_id == later.session.visit_id,
            "waited": int((timezone.now() - job.dispatched).total_seconds()) if job else None,
            "error": _job_error_words(job) if job and job.state == Job.FAILED else None})
    return _comparison_page(request, p, earlier, later, comp, scans)


def _comparison_job(earlier, later) -> Job:
    """The pair's comparison job (asked for by a POST), made and sent if there is none; a failed one, or a
    succeeded one whose result is gone, queued again."""
    job = pipeline.comparison_job_of(earlier, later)
    if job is None:  # a new one (without a broker it has run, and may have failed, by now: shown as such)
        return pipeline.request_comparison(earlier, later)
    gone = job.state == Job.SUCCEEDED and not Comparison.objects.filter(earlier=earlier, later=later).exists()
    if gone or job.state == Job.FAILED:
        try:
            job = pipeline.rerun(job)
        except pipeline.JobError:  # another request re-queued it first: show that one's progress
            job.refresh_from_db()
    return job


def _job_error_words(job) -> str:
    """A failed comparison's reason, without the traceback an unexpected fault keeps for the technician."""
    first = (job.error or "").splitlines()[0] if job.error else ""
    return first.removeprefix("comparison: ") or "the comparison could not be computed"


def comparison_index_rows(comp, mdc) -> list[dict]:
    """Every index's change between the comparison's two scans, in the clinic's words, table order."""
    from analysis.repeatability import index_changes

    facing = comp.report.get("facing") or {}
    changes = index_changes(comp.earlier.indices or {}, comp.later.indices or {}, mdc,
                            sides_agree=facing.get("consistent", True))
    rows = []
    for key in labels.TABLE_KEYS:
        c = changes.get(key)
        if c is None:
            continue
        ix = labels.index(key)
        words = labels.change_texts(key, c)
        rows.append({"label": ix.label, "unit": ix.unit, "meaning": ix.meaning, "growth": ix.growth,
                     "earlier": words["earlier"], "later": words["later"],
                     "change": words["change"], "mdc": c["mdc"],
                     "exceeds_mdc": c["exceeds_mdc"], "no_verdict": c.get("no_verdict")})
    return rows


def _comparison_page(request, p, earlier, later, comp, scans):
    mdc = cached_mdc(p.clinic)
    noise = noise_state(p.clinic)
    facing = comp.report.get("facing") or {}
    repeat = earlier.session.visit_id == later.session.visit_id
    verdict = verdict_of(p.clinic, earlier, later, "Same-day re-scan" if repeat else "Between these scans", mdc,
                       noise, sides_agree=facing.get("consistent", True), growth=comp.report.get("growth"))
    index_rows = comparison_index_rows(comp, mdc)
    regions = []
    for name, stats in (comp.report.get("regions") or {}).items():
        m = (mdc.get(f"regions.{name}.mean") or {}).get("mdc")
        mean = stats.get("mean")
        regions.append({"name": labels.region(name), "mean": mean, "p05": stats.get("p05"), "p95": stats.get("p95"),
                        "mdc": m, "beyond": None if m is None or mean is None else abs(mean) > m})
    growth = comp.report.get("growth")
    growth_rows = [{"label": name, "earlier": growth["earlier"].get(key), "later": growth["later"].get(key),
                    "change": growth["change"].get(key)} for key, name in labels.GROWTH_FIGURES] if growth else []
    return render(request, "clinic/comparison.html", {
        **patient_context(p), "earlier": earlier, "later": later, "earlier_date": earlier.session.visit.date,
        "later_date": later.session.visit.date, "comparison": comp, "report": comp.report,
        "regions": regions, "index_rows": index_rows, "facing": facing, "noise": noise, "growth_rows": growth_rows,
        "repeat": repeat, "verdict": verdict, "scans": scans,
        "pictures": _pictures("comparison", comp),
        "quality": {"earlier": scan_quality(earlier), "later": scan_quality(later)}})


@login_required
def rig(request, serial):
    """A rig: its calibrations, every camera's stability history and, for who may manage them, its API keys."""
    return _rig_page(request, get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)),
                                                serial=serial))


def _calibration_due(r, now) -> dict:
    """When the rig's next calibration is due: its latest good calibration plus its interval (the rule the
    scheduled check flags rigs by), and whether that date has passed."""
    from datetime import timedelta

    last = r.current_calibration
    if last is None:
        return {"last": None, "due": None, "overdue": True}
    due = last.calibrated_at + timedelta(days=r.recalibration_interval_days)
    return {"last": last.calibrated_at, "due": due, "overdue": due < now,
            "in_words": span_words(now.date(), due.date()) if due >= now else span_words(due.date(), now.date())}


def _rig_page(request, r, new_key=None, replaced_key=None):
    calibrations = list(r.calibrations.all().order_by("calibrated_at"))
    by_camera = {}  # every camera's checks in one query
    for check in (StabilityCheck.objects.filter(camera__rig=r).annotate(calibrated_at=F("calibration__calibrated_at"))
                  .order_by("calibration__calibrated_at")):
        by_camera.setdefault(check.camera_id, []).append(check)
    cams = []
    for cam in r.cameras.all():
        checks = by_camera.get(cam.pk, [])
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
        "calibration_due": _calibration_due(r, timezone.now()),
        "may_manage_keys": may_manage_keys, "keys": r.keys.order_by("-created") if may_manage_keys else [],
        "new_key": new_key, "replaced_key": replaced_key, "form_token": uuid.uuid4().hex})


@login_required
@require_POST
def issue_rig_key(request, serial):
    """A new API key for the rig, shown on this one answer only (only its hash is kept).

    One click makes one live key: the form's token remembers the key it issued, and a second post of the same
    form (a double click, whose first answer the browser drops, or a reload of the answer) revokes that key and
    shows a new one, so no live key is left that nobody saw."""
    try:
        check_param(serial, "serial", 64)
    except Invalid as exc:
        raise BadRequest(str(exc)) from None
    r = get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)), serial=serial)
    _require_role(request, r.clinic_id)  # as the API's (before a repeat revokes anything)
    revoked = None
    token = _posted_token(request)
    key = f"form-once:{request.user.pk}:{token}" if token else None
    if key is not None and not once.claim(key, FORM_TOKEN_SECONDS):
        earlier = once.first_outcome(key)  # the prefix of the key the first post issued
        if earlier and r.keys.filter(prefix=earlier, revoked__isnull=True).update(revoked=timezone.now()):
            revoked = earlier
    try:
        issued = _run_api(api.new_rig_key, request, serial)
    except BaseException:
        if key is not None:
            once.release(key)
        raise
    if key is not None:
        once.settle(key, issued["key"][:10], FORM_TOKEN_SECONDS)  # its prefix (RigKey.issue)
    return _rig_page(request, r, new_key=issued["key"], replaced_key=revoked)


@login_required
@require_POST
def revoke_rig_key(request, serial, prefix):
    _run_api(api.revoke_rig_key, request, serial, prefix)
    messages.success(request, f"Key {prefix}… revoked: the rig can no longer upload with it.")
    return redirect("rig", serial=serial)


MEASURES = (("zrot_px", "ZROT"), ("rot_px", "ROT"), ("spr_px", "SPR"), ("arm_px", "ARM"))


@login_required
def rig_stability_chart(request, serial):
    """Every measure of every camera over the rig's calibrations against its threshold (SVG): drawn once per
    state of the rig's checks, then served from storage (as the patients' trend pictures)."""
    import hashlib

    r = get_object_or_404(Rig.objects.filter(clinic__in=clinics_of(request.user)), serial=serial)
    by_camera = {}  # every check of the rig in one query
    for check in (StabilityCheck.objects.filter(camera__rig=r).annotate(calibrated_at=F("calibration__calibrated_at"))
                  .order_by("calibration__calibrated_at")):
        by_camera.setdefault(check.camera_id, []).append(check)
    cams = [c for c in r.cameras.all() if by_camera.get(c.pk)]
    if not cams:
        raise Http404("no stability check yet")
    series = {field: [(cam.name, [(c.calibrated_at, getattr(c, field) / (c.thresholds or {}).get(
        field, c.threshold_px)) for c in by_camera[cam.pk] if getattr(c, field) is not None]) for cam in cams]
        for field, _ in MEASURES}
    state = json.dumps(series, sort_keys=True, default=str)
    name = f"charts/rig-{r.pk}/stability-{hashlib.sha256(state.encode()).hexdigest()[:24]}.svg"
    if default_storage.exists(name):
        return FileResponse(default_storage.open(name, "rb"), content_type="image/svg+xml")
    data = _stability_svg(series).encode()
    _store_replacing_older_states(name, data)
    return HttpResponse(data, content_type="image/svg+xml")


def _stability_svg(series) -> str:
    from matplotlib.figure import Figure  # not pyplot: its global state is not safe across request threads

    fig = Figure(figsize=(15, 3.6))
    axes = fig.subplots(1, 4, sharex=True)
    for ax, (field, title) in zip(axes, MEASURES):
        for cam, points in series[field]:
            ax.plot([x for x, _ in points], [y for _, y in points], "o-", lw=1, ms=3, label=cam)
        ax.axhline(1.0, color="#c0392b", lw=1, ls="--")
        ax.set_title(f"{title} / threshold (above 1: unstable)", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[-1].legend(fontsize=6, ncol=2, loc="upper left", bbox_to_anchor=(1.02, 1))
    fig.autofmt_xdate()
    fig.tight_layout()
    buf = io.StringIO()
    fig.savefig(buf, format="svg")
    return buf.getvalue()


@login_required
def picture(request, kind, pk, name):
    """A stored picture of a reconstruction or a comparison the user may see."""
    if kind == "reconstruction":
        obj = get_object_or_404(_reconstructions(request.user), pk=pk)
    elif kind == "comparison":
        obj = get_object_or_404(Comparison.objects.filter(captures_of(clinics_of(request.user), "later__session")),
                                pk=pk)
    else:
        raise Http404(kind)
    stored = (obj.pictures or {}).get(name)
    if not stored or not default_storage.exists(stored):
        raise Http404(f"no picture {name!r}")
    return FileResponse(default_storage.open(stored, "rb"), content_type="image/png")


@login_required
def picture_page(request, kind, pk, name):
    """A picture at full size, under the name of the patient it shows."""
    if kind == "reconstruction":
        obj = get_object_or_404(_reconstructions(request.user), pk=pk)
        rec, subject = obj, None
    elif kind == "comparison":
        obj = get_object_or_404(Comparison.objects.filter(captures_of(clinics_of(request.user), "later__session")),
                                pk=pk)
        rec, subject = obj.later, obj
    else:
        raise Http404(kind)
    if name not in (obj.pictures or {}):
        raise Http404(f"no picture {name!r}")
    v = rec.session.visit
    if v is None:
        raise Http404("not a patient's picture")
    title, alt = labels.picture(name)
    return render(request, "clinic/picture.html", {
        **patient_context(v.patient, v.date), "visit": v, "title": title, "alt": alt,
        "src": reverse("picture", args=[kind, pk, name]), "comparison": subject,
        "earlier_date": subject.earlier.session.visit.date if subject else None})


@login_required
@require_POST
def rerun(request, job_id):
    job = get_object_or_404(Job.objects.filter(jobs_of(clinics_of(request.user))), uid=job_id)
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


# --- patients and visits, made and edited in the pages ------------------------------------------

class PatientForm(forms.ModelForm):
    class Meta:
        model = Patient
        fields = ["clinic", "identifier", "name", "date_of_birth", "sex", "notes"]
        widgets = {"date_of_birth": forms.DateInput(attrs={"type": "date"}), "notes": forms.Textarea(attrs={"rows": 3})}
        labels = {"identifier": "Identifier (the clinic's patient number)"}

    def __init__(self, *args, clinics=None, **kw):
        super().__init__(*args, **kw)
        self.fields["notes"].max_length = MAX_NOTES  # as the API's limit
        self.fields["notes"].validators.append(validators.MaxLengthValidator(MAX_NOTES))
        if self.instance.pk:
            del self.fields["clinic"]
        else:
            self.fields["clinic"].queryset = clinics
            if clinics is not None and clinics.count() == 1:
                self.fields["clinic"].initial = clinics.first()

    def clean_date_of_birth(self):
        from django.utils import timezone

        born = self.cleaned_data.get("date_of_birth")
        if born and born > timezone.localdate():
            raise forms.ValidationError("The date of birth cannot be in the future.")
        return born

    def clean(self):
        data = super().clean()
        clinic = data.get("clinic") or getattr(self.instance, "clinic", None)
        ident = data.get("identifier")
        if clinic and ident and Patient.objects.filter(clinic=clinic, identifier=ident).exclude(
                pk=self.instance.pk).exists():
            self.add_error("identifier", f"{clinic.name} already has a patient with the identifier {ident}.")
        return data


class VisitForm(forms.ModelForm):
    class Meta:
        model = Visit
        fields = ["date", "reason", "notes", "next_visit_due"]
        widgets = {"date": forms.DateInput(attrs={"type": "date"}), "notes": forms.Textarea(attrs={"rows": 4}),
                   "next_visit_due": forms.DateInput(attrs={"type": "date"})}
        labels = {"next_visit_due": "Next visit due"}

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.fields["next_visit_due"].help_text = (
            "Optional. Past this date the patient is listed as overdue on the worklist (without it: "
            f"{getattr(settings, 'FOLLOW_UP_MONTHS', 6)} months after this visit).")
        self.fields["notes"].max_length = MAX_NOTES  # as the API's limit
        self.fields["notes"].validators.append(validators.MaxLengthValidator(MAX_NOTES))

    def clean_date(self):
        d = self.cleaned_data.get("date")
        born = self.instance.patient.date_of_birth if self.instance.patient_id else None
        if d and born and d < born:
            raise forms.ValidationError("The visit cannot be before the patient's date of birth.")
        return d

    def clean(self):
        data = super().clean()
        d, due = data.get("date"), data.get("next_visit_due")
        if d and due and due <= d:
            self.add_error("next_visit_due", "The next visit must be due after this visit.")
        return data


def _form_page(request, form, title, context=None, status=200):
    return render(request, "clinic/form.html", {"form": form, "title": title, **(context or {})}, status=status)


FORM_TOKEN_SECONDS = 3600  # how long a form's one-time token is remembered (a double click, a re-post, a reload)


def _posted_token(request) -> str | None:
    """The one-time token the posted form carries, or None (an old page, a script, a malformed one)."""
    posted = request.POST.get("form_token", "")
    return posted if 8 <= len(posted) <= 64 and posted.isalnum() else None


def _form_token(request) -> str:
    """The one-time token a creating form carries: the posted one (a form shown again with its errors keeps it)
    or a new one."""
    return _posted_token(request) or uuid.uuid4().hex


def _once(request, make):
    """``make()``'s answer, made once per form: a second post of the same form (a double click on Save, a
    browser re-posting after a slow answer, a reload of the answer) is sent where the first one's answer went
    instead of making a second patient or visit. A form whose answer was not a redirect (it had errors) may be
    posted again. The tokens live in the cache, which production shares between processes (CACHE_URL)."""
    token = _posted_token(request)
    if token is None:
        return make()  # no token (an old page, a script): as before
    key = f"form-once:{request.user.pk}:{token}"
    if not once.claim(key, FORM_TOKEN_SECONDS):
        done = once.first_outcome(key)  # where the first post went, once it is saved
        if done is None:  # the first had errors (or the cache forgot it): this one is made afresh
            return _once(request, make)
        if done:
            return redirect(done)
        return _refused(request, "This form was sent twice and the first is still being saved: look for what it "
                                 "made in the patient list in a moment before sending it again.", 409)
    try:
        response = make()
    except BaseException:
        once.release(key)
        raise
    if response.status_code == 302:
        once.settle(key, response["Location"], FORM_TOKEN_SECONDS)
    else:
        once.release(key)
    return response


def record_version(form) -> str:
    """What an edit form was drawn from: a short hash of each field's value as stored then, in the form's field
    order (so that a refused save can name the fields someone else changed)."""
    return ".".join(_short_hash(form.initial.get(name), 8) for name in form.fields)


def changed_since(form, based_on: str) -> list:
    """The fields of ``form`` (bound to the stored row) whose stored value is not the one ``based_on`` (a
    :func:`record_version`) was drawn from; all of them if ``based_on`` is not such a version."""
    then, now = based_on.split("."), record_version(form).split(".")
    names = list(form.fields)
    return [n for k, n in enumerate(names) if len(then) != len(names) or then[k] != now[k]]


def _edit(request, form_class, model, pk, title, ctx, done, **form_kw):
    """An edit form for the row ``pk`` of ``model``. The row is locked and read again when the form is saved;
    if it changed since the form was drawn (``based_on``), nothing is saved and the form comes back (409) naming
    what changed meanwhile and its value now, with the person's own entries kept: saving again then overwrites
    knowingly."""
    if request.method != "POST":
        form = form_class(instance=model.objects.get(pk=pk), **form_kw)
        return _form_page(request, form, title, {**ctx, "based_on": record_version(form)})
    with transaction.atomic():
        row = model.objects.select_for_update().get(pk=pk)
        stored = form_class(instance=row, **form_kw)
        form = form_class(request.POST, instance=row, **form_kw)
        now = record_version(stored)
        based_on = request.POST.get("based_on")
        if based_on is not None and based_on != now and not (form.is_valid() and not form.has_changed()):
            # (the entries equal what is stored: this form's own second post, a double click, or the same edit
            # made twice: nothing is lost, it is answered as saved)
            changed = [f"{stored[name].label.lower()} (now {stored.initial.get(name) or 'empty'})"
                       for name in changed_since(stored, based_on)]
            form.is_valid()
            form.add_error(None, "Someone else saved this record since you opened the form; nothing was saved. "
                                 + ("Changed meanwhile: " + "; ".join(changed) + ". " if changed else "")
                                 + "Check your entries below and save again to keep them.")
            return _form_page(request, form, title, {**ctx, "based_on": now}, status=409)
        if not form.is_valid():
            return _form_page(request, form, title, {**ctx, "based_on": based_on or now}, status=400)
        if form.has_changed():
            form.save()
    return done()


def _editable_clinics(request):
    return clinics_of(request.user).filter(pk__in=[c.pk for c in clinics_of(request.user)
                                                   if _may(request, c.pk, EDIT_PATIENTS)])


@login_required
def new_patient(request):
    clinics = _editable_clinics(request)
    if not clinics.exists():
        raise PermissionDenied("you are not a member of any clinic")
    form = PatientForm(request.POST or None, clinics=clinics)
    token = {"form_token": _form_token(request)}
    if request.method != "POST":
        return _form_page(request, form, "New patient", token)

    def create():
        if not form.is_valid():
            return _form_page(request, form, "New patient", token, status=400)
        _require_role(request, form.cleaned_data["clinic"].pk, EDIT_PATIENTS)
        try:
            with transaction.atomic():
                p = form.save()
        except IntegrityError:  # the same identifier saved by another request since the form's check
            form.add_error("identifier", f"identifier {form.cleaned_data['identifier']}: the clinic already has "
                                         f"a patient with it (saved a moment ago)")
            return _form_page(request, form, "New patient", token, status=400)
        messages.success(request, f"Patient {p.name} ({p.identifier}) created.")
        return redirect("patient", patient_id=p.pk)

    return _once(request, create)


@login_required
def edit_patient(request, patient_id):
    p = get_object_or_404(_patients(request.user), pk=patient_id)
    _require_role(request, p.clinic_id, EDIT_PATIENTS)
    def saved():
        messages.success(request, "Patient saved.")
        return redirect("patient", patient_id=p.pk)

    try:
        return _edit(request, PatientForm, Patient, p.pk, f"Edit {p.name}", patient_context(p), saved)
    except IntegrityError:  # an identifier taken by another request since the form's check
        form = PatientForm(request.POST, instance=Patient.objects.get(pk=p.pk))
        form.is_valid()
        form.add_error("identifier", "this identifier was given to another patient a moment ago")
        return _form_page(request, form, f"Edit {p.name}",
                          {**patient_context(p), "based_on": request.POST.get("based_on")}, status=400)


@login_required
def new_visit(request, patient_id):
    p = get_object_or_404(_patients(request.user), pk=patient_id)
    _require_role(request, p.clinic_id, EDIT_PATIENTS)
    form = VisitForm(request.POST or None, instance=Visit(patient=p, clinician=request.user))
    ctx = {**patient_context(p), "form_token": _form_token(request)}
    if request.method != "POST":
        return _form_page(request, form, "New visit", ctx)

    def create():
        if not form.is_valid():
            return _form_page(request, form, "New visit", ctx, status=400)
        v = form.save()
        messages.success(request, f"Visit of {v.date} created: the rig can now upload its scans for it.")
        return redirect("visit", visit_id=v.pk)

    return _once(request, create)


@login_required
def edit_visit(request, visit_id):
    v = get_object_or_404(Visit.objects.filter(patient__clinic__in=clinics_of(request.user)), pk=visit_id)
    _require_role(request, v.patient.clinic_id, EDIT_PATIENTS)
    def saved():
        messages.success(request, "Visit saved.")
        return redirect("visit", visit_id=v.pk)

    return _edit(request, VisitForm, Visit, v.pk, f"Edit the visit of {v.date}", patient_context(v.patient, v.date),
                 saved)
