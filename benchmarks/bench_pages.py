"""Server time of every clinician page with 10 000 patients and 50 000 visits in PostgreSQL (issue 28 §4).

Makes a PostgreSQL database of its own (``torsoscan_bench_pages_<pid>``, dropped at the end unless ``--keep``),
migrates it and seeds, with ``bulk_create``:

- 4 clinics (50 / 25 / 15 / 10 % of the patients), each with a rig of 20 cameras, 24 monthly calibrations and
  their stability checks, and a few members; the measured user administers the largest clinic and is a
  clinician in the second, so every query is scoped to 75 % of the rows;
- the patients and their visits (1 to 25 a patient, long-tailed, 4-8 months apart; some today; half with a
  next visit due date);
- a capture session for 60 % of the visits (a same-day re-scan for 5 % of those), each with its reconstruction
  job (98 % succeeded, 2 % failed) and, when it succeeded, a reconstruction whose ``indices`` and pictures are
  those the real analysis made of a synthetic torso (``tests/test_browser_comparison.torso_ply`` through
  ``clinic.analysis_step.analyse_reconstruction``, once, then copied into every row by the database);
- the comparisons the pipeline makes (``pipeline.earlier_reconstructions``: every torso against the latest of
  each earlier visit and the earlier scans of its own visit), each carrying the report of one real comparison.

Then times every clinician page with Django's test ``Client`` (in this process, DEBUG off, so no query log
slows it down) against that database: ``--repeats`` requests each after two warm-up requests, p50 / p95 / max
server time in ms, and the SQL queries of one more request (Django's ``CaptureQueriesContext``); the first
request's time is reported apart (it fills the caches: the clinic's MDC, the trend picture, the stability chart,
a PDF report's drawing). The reports are timed as a clinician downloads them again: the footer naming who produced
the report and when is written on each download, the pages are drawn once per state of what they show.
A page slower than 2 s a request is timed fewer times (at least 3, about 30 s in all).

    .venv/bin/python benchmarks/bench_pages.py [--patients 10000] [--visits 50000] [--repeats 50] \\
        [--keep] [--reuse NAME] [--only WORD ...] [--json OUT]

``--keep`` keeps the database (its name is printed); ``--reuse NAME`` times a kept one again (migrating it
first, so a new migration is measured on the same rows).
"""

import argparse
import datetime as dt
import json
import os
import secrets
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from provenance import provenance  # noqa: E402
from tests.pg_server import PG, run_sql  # noqa: E402

FIRST = ["Alice", "Ben", "Chloé", "David", "Emma", "Farid", "Grace", "Hugo", "Inès", "Jonas", "Kira", "Liam", "Maya",
         "Noah", "Olga", "Pablo", "Quinn", "Rosa", "Sami", "Tara", "Uma", "Victor", "Wen", "Xavier", "Yara", "Zoé",
         "Anna", "Bruno", "Clara", "Dmitri", "Elif", "Finn", "Greta", "Hamid", "Ida", "Jakub", "Lena", "Marco",
         "Nina", "Oscar"]
LAST = ["Smith", "Moreau", "Novak", "Rossi", "García", "Müller", "Kowalski", "Jensen", "Dubois", "Silva", "Nakamura",
        "Okafor", "Haddad", "Larsen", "Petrov", "Costa", "Bauer", "Lindqvist", "Fischer", "Martin", "Bernard",
        "Horvat", "Ivanova", "Kim", "Lopez", "Meyer", "Nowak", "Olsen", "Perez", "Quist", "Richter", "Schmidt",
        "Tanaka", "Urban", "Vogel", "Weber", "Yilmaz", "Zimmer", "Abbott", "Brennan", "Carter", "Doyle", "Evans",
        "Foster", "Gallo", "Hughes", "Ibsen", "Jovanović", "Keller", "Łukasik", "Marsh", "Nash", "Ortiz", "Price",
        "Reyes", "Sato", "Torres", "Vance", "Walsh", "Young"]
CLINICS = [("North", "N", 0.50), ("South", "S", 0.25), ("East", "E", 0.15), ("West", "W", 0.10)]
CAMERAS = [f"{arm}{i}" for arm in "ABCD" for i in range(1, 6)]
MAX_VISITS = 25
SESSION_SHARE, REPEAT_SHARE, FAILED_SHARE = 0.60, 0.05, 0.02
CALIBRATIONS = 24
SLOW_S = 2.0  # a page slower than this a request is timed fewer times
BATCH = 5000


def setup_django(dbname: str, var: Path):
    os.environ.update({
        "DJANGO_SETTINGS_MODULE": "clinic.settings", "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{dbname}",
        "TORSOSCAN_VAR": str(var), "CELERY_BROKER_URL": "", "DEBUG": "false",
        "SECRET_KEY": secrets.token_urlsafe(50), "SECURE_SSL_REDIRECT": "false", "SESSION_COOKIE_SECURE": "false",
        "CSRF_COOKIE_SECURE": "false", "SECURE_HSTS_SECONDS": "0", "LOG_LEVEL": "WARNING"})
    import django

    django.setup()


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# --- seeding ---------------------------------------------------------------------------------------------------------

def visit_counts(rng, patients: int, visits: int) -> np.ndarray:
    """Visits per patient: at least 1, at most MAX_VISITS, long-tailed, summing to ``visits``."""
    counts = np.ones(patients, dtype=int)
    weights = rng.gamma(0.8, size=patients)
    counts += rng.multinomial(visits - patients, weights / weights.sum())
    over = counts - MAX_VISITS
    extra = int(over[over > 0].sum())
    counts = np.minimum(counts, MAX_VISITS)
    while extra:
        k = int(rng.integers(patients))
        if counts[k] < MAX_VISITS:
            counts[k] += 1
            extra -= 1
    counts[0] = MAX_VISITS  # the first patient of the largest clinic: the longest history, measured below
    surplus = int(counts.sum()) - visits
    k = patients - 1
    while surplus > 0:
        if counts[k] > 1:
            counts[k] -= 1
            surplus -= 1
        k = k - 1 if k > 1 else patients - 1
    return counts


def seed(args):
    from django.contrib.auth.hashers import make_password
    from django.contrib.auth.models import User
    from django.core.files.base import ContentFile
    from django.db import connection

    from clinic.analysis_step import analyse_reconstruction, compare_reconstructions
    from clinic.models import (Calibration, Camera, CaptureSession, Clinic, Comparison, Job, Member, Patient,
                               Reconstruction, Rig, StabilityCheck, Visit)
    from tests.test_browser_comparison import torso_ply

    rng = np.random.default_rng(args.seed)
    today = dt.date.today()
    now = dt.datetime.now(dt.timezone.utc)
    t0 = time.perf_counter()

    # clinics, users, members, rigs
    password = make_password("bench-pages")
    clinics = [Clinic.objects.create(name=name) for name, _, _ in CLINICS]
    lee = User.objects.create(username="drlee", password=password, first_name="Dr", last_name="Lee")
    users = {c.pk: [] for c in clinics}
    members = [Member(clinic=clinics[0], user=lee, role=Member.ADMINISTRATOR),
               Member(clinic=clinics[1], user=lee, role=Member.CLINICIAN)]
    for c, staff in zip(clinics, (14, 8, 5, 5)):
        for k in range(staff):
            u = User.objects.create(username=f"{c.name.lower()}{k:02d}", password=password)
            role = (Member.ADMINISTRATOR, Member.TECHNICIAN)[k] if k < 2 else Member.CLINICIAN
            members.append(Member(clinic=c, user=u, role=role))
            users[c.pk].append(u)
    users[clinics[0].pk].append(lee)
    Member.objects.bulk_create(members)
    rigs = []
    for c in clinics:
        desc = {"format": "torso-rig/1", "serial": f"RIG-{c.name.upper()}",
                "arms": [{"id": a, "cameras": [f"{a}{i}" for i in range(1, 6)], "projector": f"P{a}"} for a in "ABCD"],
                "cameras": {n: {"width": 3000, "height": 2000, "pixel_size_mm": 0.0047, "nominal_focal_mm": 35.0}
                            for n in CAMERAS}}
        rig = Rig.objects.create(clinic=c, serial=desc["serial"], description=desc)
        cams = Camera.objects.bulk_create([Camera(rig=rig, name=n, arm=n[0], position=int(n[1:]) - 1, width=3000,
                                                  height=2000, pixel_size_mm=0.0047, nominal_focal_mm=35.0)
                                           for n in CAMERAS])
        cals = Calibration.objects.bulk_create([Calibration(
            rig=rig, file=f"calibrations/{rig.serial}-{k}.json",
            calibrated_at=now - dt.timedelta(days=30 * (CALIBRATIONS - k)),
            figures={"sigma0": 0.9, "residual_rms_px": {n: round(0.15 + 0.05 * rng.random(), 3) for n in CAMERAS},
                     "dropped": {n: int(rng.integers(3)) for n in CAMERAS}, "warnings": []},
            sigmas={n: {"f": 0.4, "cx": 0.3, "cy": 0.3} for n in CAMERAS}) for k in range(CALIBRATIONS)])
        StabilityCheck.objects.bulk_create([StabilityCheck(
            camera=cam, calibration=cals[k], reference=cals[k - 1], zrot_px=0.2, rot_px=0.3, spr_px=0.25, arm_px=0.4,
            threshold_px=1.0, thresholds={"zrot_px": 1.0, "rot_px": 1.0, "spr_px": 1.0, "arm_px": 1.0},
            exceeds=[], stable=True) for k in range(1, CALIBRATIONS) for cam in cams])
        rigs.append(rig)

    # patients
    share = np.array([s for _, _, s in CLINICS])
    per_clinic = np.floor(share * args.patients).astype(int)
    per_clinic[0] += args.patients - per_clinic.sum()
    patients = []
    for c, (_, prefix, _), n in zip(clinics, CLINICS, per_clinic):
        for k in range(n):
            born = today - dt.timedelta(days=int(rng.integers(6 * 365, 17 * 365)))
            patients.append(Patient(clinic=c, identifier=f"{prefix}-{k + 1:06d}",
                                    name=f"{FIRST[rng.integers(len(FIRST))]} {LAST[rng.integers(len(LAST))]}",
                                    date_of_birth=born, sex="FM"[int(rng.integers(2))]))
    Patient.objects.bulk_create(patients, batch_size=BATCH)
    log(f"{len(patients)} patients in {time.perf_counter() - t0:.0f} s")

    # visits: backwards from the latest, 4-8 months apart
    counts = visit_counts(rng, args.patients, args.visits)
    today_patients = set(rng.choice(np.arange(1, args.patients), size=min(60, args.patients - 1), replace=False))
    visits = []
    for k, (p, n) in enumerate(zip(patients, counts)):
        day = today if k in today_patients else today - dt.timedelta(days=int(rng.integers(0, 400)))
        dates = []
        for _ in range(n):
            dates.append(day)
            day -= dt.timedelta(days=int(rng.integers(120, 240)))
        staff = users[p.clinic_id]
        for d in reversed(dates):
            due = d + dt.timedelta(days=int(rng.integers(150, 200))) if rng.random() < 0.5 else None
            visits.append(Visit(patient=p, date=d, clinician=staff[int(rng.integers(len(staff)))],
                                reason=("follow-up", "first visit", "brace check", "after growth spurt")[
                                    int(rng.integers(4))], next_visit_due=due,
                                created=dt.datetime.combine(d, dt.time(9), dt.timezone.utc)))
    Visit.objects.bulk_create(visits, batch_size=BATCH)
    log(f"{len(visits)} visits in {time.perf_counter() - t0:.0f} s")

    # capture sessions and their reconstruction jobs
    rig_of = {r.clinic_id: r for r in rigs}
    sessions = []
    for v in visits:
        if v.patient is patients[0] or rng.random() < SESSION_SHARE:
            scans = 2 if (v.patient is patients[0] and len(sessions) % 3 == 0) or rng.random() < REPEAT_SHARE else 1
            for s in range(scans):
                at = dt.datetime.combine(v.date, dt.time(10, 5 * s), dt.timezone.utc)
                rig = rig_of[v.patient.clinic_id]
                sessions.append(CaptureSession(rig=rig, kind="torso", visit=v,
                                               manifest={"images": [], "rig": rig.serial},
                                               manifest_sha256="0" * 64, idempotency_key=f"v{v.pk}-{s}",
                                               captured_at=at.isoformat(), state=CaptureSession.FINALIZED,
                                               created=at, finalized=at))
    CaptureSession.objects.bulk_create(sessions, batch_size=BATCH)
    jobs = []
    for s in sessions:
        failed = s.visit.patient is not patients[0] and rng.random() < FAILED_SHARE
        jobs.append(Job(kind=Job.RECONSTRUCTION, rig=s.rig, session=s, state=Job.FAILED if failed else Job.SUCCEEDED,
                        stage="done", percent=100, attempt=1, error="registration: too few matches" if failed else "",
                        created=s.created, started=s.created, finished=s.created + dt.timedelta(minutes=3),
                        dispatched=s.created))
    Job.objects.bulk_create(jobs, batch_size=BATCH)
    log(f"{len(sessions)} sessions and jobs in {time.perf_counter() - t0:.0f} s")

    # one torso analysed for real, then its indices and pictures copied into every reconstruction
    report = {"problems": [], "arms": {a: {"points": 40000, "sigma_mm_median": 0.08} for a in "ABCD"},
              "registration": {"pairs": [{"a": a, "b": b, "average_normal_distance_mm": 0.31,
                                          "overlap_matched_fraction": 0.94} for a, b in ("AB", "BC", "CD", "DA")]}}
    recs = [Reconstruction(job=j, session=j.session, torso="", report_file="", report=report, status="ok",
                           points=160000, created=j.finished) for j in jobs if j.state == Job.SUCCEEDED]
    Reconstruction.objects.bulk_create(recs, batch_size=BATCH)
    real = [r for r in recs if r.session.visit.patient is patients[0]]
    first, second = real[0], next(r for r in real if r.session.visit_id != real[0].session.visit_id)
    for k, rec in enumerate((first, second)):
        rec.torso.save("torso.ply", ContentFile(torso_ply((5.0, 10.0)[k], k)), save=False)
        rec.report_file.save("report.json", ContentFile(json.dumps(report).encode()), save=False)
        rec.save()
        analyse_reconstruction(rec)
    log(f"{len(recs)} reconstructions; two torsos analysed for real in {time.perf_counter() - t0:.0f} s")
    with connection.cursor() as cur:
        cur.execute("UPDATE clinic_reconstruction r SET indices = s.indices, pictures = s.pictures, torso = s.torso, "
                    "report_file = s.report_file FROM clinic_reconstruction s WHERE s.id = %s AND r.id <> %s "
                    "AND r.id <> %s", [first.pk, first.pk, second.pk])
    real_comparison = compare_reconstructions(first, second)

    # the comparisons the pipeline makes
    by_patient = {}
    for r in recs:
        by_patient.setdefault(r.session.visit.patient_id, []).append(r)
    comparisons = []
    for rs in by_patient.values():
        rs.sort(key=lambda r: (r.session.visit.date, r.session.visit_id, r.created, r.pk))
        for j, later in enumerate(rs):
            latest = {}
            for e in rs[:j]:
                if e.session.visit_id == later.session.visit_id:
                    latest[("same", e.pk)] = e
                else:
                    latest[e.session.visit_id] = e  # the later one of a visit wins: its latest scan
            for e in latest.values():
                if (e.pk, later.pk) != (first.pk, second.pk):
                    comparisons.append(Comparison(earlier=e, later=later, created=later.created,
                                                  deformation=real_comparison.deformation.name,
                                                  repeat=e.session.visit_id == later.session.visit_id))
    Comparison.objects.bulk_create(comparisons, batch_size=BATCH)
    with connection.cursor() as cur:
        cur.execute("UPDATE clinic_comparison c SET report = s.report, pictures = s.pictures FROM clinic_comparison s "
                    "WHERE s.id = %s AND c.id <> %s", [real_comparison.pk, real_comparison.pk])
    log(f"{len(comparisons) + 1} comparisons in {time.perf_counter() - t0:.0f} s")
    with connection.cursor() as cur:
        cur.execute("VACUUM ANALYZE")
    log(f"seeded in {time.perf_counter() - t0:.0f} s")


# --- timing ----------------------------------------------------------------------------------------------------------

def targets():
    """The pages to time: (name, url, headers) for the measured user's largest clinic."""
    from django.db.models import Count
    from django.urls import reverse

    from clinic.models import CaptureSession, Clinic, Comparison, Job, Patient, Reconstruction, Rig, RigKey, Visit

    north = Clinic.objects.get(name="North")
    rig = Rig.objects.get(clinic=north)
    heavy = Patient.objects.get(clinic=north, identifier="N-000001")
    typical = (Patient.objects.filter(clinic=north).annotate(n=Count("visits")).filter(n=5)
               .order_by("identifier").first())
    recs = list(Reconstruction.objects.filter(session__visit__patient=heavy, job__state=Job.SUCCEEDED)
                .order_by("session__visit__date", "session__visit_id", "created", "pk"))
    last_visit = recs[-1].session.visit
    comp = Comparison.objects.filter(earlier__session__visit=recs[0].session.visit, later=recs[-1]).first()
    session = CaptureSession.objects.filter(visit=last_visit).order_by("created").first()
    job = Job.objects.get(session=session)
    _, key = RigKey.issue(rig)
    bearer = {"HTTP_AUTHORIZATION": f"Bearer {key}"}
    q = Patient.objects.filter(clinic=north).values_list("name", flat=True).first().split()[-1]
    n_heavy = Visit.objects.filter(patient=heavy).count()
    picture = sorted(recs[-1].pictures)[0]
    return [
        ("worklist and patient list (home)", reverse("patients"), {}),
        (f"patient search (q={q})", reverse("patients") + f"?q={q}", {}),
        (f"patient history ({n_heavy} visits, {len(recs)} scans)", reverse("patient", args=[heavy.pk]), {}),
        ("patient history (5 visits)", reverse("patient", args=[typical.pk]), {}),
        ("patient trend picture (cached)", reverse("patient_trend", args=[heavy.pk]), {}),
        ("visit page", reverse("visit", args=[last_visit.pk]), {}),
        ("comparison page (first and last scan)",
         reverse("comparison", args=[heavy.pk]) + f"?earlier_scan={comp.earlier_id}&later_scan={recs[-1].pk}", {}),
        ("picture page (a torso view)", reverse("picture_page", args=["reconstruction", recs[-1].pk, picture]), {}),
        ("rig page", reverse("rig", args=[rig.serial]), {}),
        ("rig stability chart (SVG)", reverse("rig_stability_chart", args=[rig.serial]), {}),
        ("members page", reverse("members", args=[north.pk]), {}),
        ("visit report (PDF)", reverse("visit_report", args=[last_visit.pk]), {}),
        ("comparison report (PDF)", reverse("comparison_report", args=[comp.pk]), {}),
        ("API session status (rig key)", f"/api/sessions/{session.uid}", bearer),
        ("API job status (rig key)", f"/api/jobs/{job.uid}", bearer),
    ]


def time_pages(repeats: int, only=None) -> list:
    from django.contrib.auth.models import User
    from django.db import connection
    from django.test import Client
    from django.test.utils import CaptureQueriesContext

    client = Client()
    client.force_login(User.objects.get(username="drlee"))
    rows = []
    for name, url, headers in targets():
        if only and not any(o.lower() in name.lower() for o in only):
            continue
        t = time.perf_counter()
        r = client.get(url, **headers)  # the first request: caches filled, the trend picture drawn and stored
        first_ms = 1000 * (time.perf_counter() - t)
        assert r.status_code == 200, f"{name}: {url} answered {r.status_code}: {r.content[:300]!r}"
        t = time.perf_counter()
        client.get(url, **headers)  # a second warm-up: what the cache holds from the first is not the page's cost
        warm_ms = 1000 * (time.perf_counter() - t)
        slow = warm_ms > 1000 * SLOW_S
        n = max(3, min(repeats, int(30 / (warm_ms / 1000)))) if slow else repeats
        times = []
        for k in range(n):
            counted = slow and k == n - 1  # a slow page's queries are counted on its last timed request
            with CaptureQueriesContext(connection) if counted else _nothing() as queries:
                t = time.perf_counter()
                r = client.get(url, **headers)
                times.append(1000 * (time.perf_counter() - t))
            assert r.status_code == 200
        if not slow:
            with CaptureQueriesContext(connection) as queries:
                r = client.get(url, **headers)
        size = sum(len(c) for c in r.streaming_content) if r.streaming else len(r.content)
        row = {"page": name, "url": url, "requests": n, "first_ms": round(first_ms, 1),
               "p50_ms": round(float(np.percentile(times, 50)), 1), "p95_ms": round(float(np.percentile(times, 95)), 1),
               "max_ms": round(max(times), 1), "queries": len(queries), "bytes": size}
        rows.append(row)
        log(f"{name}: p50 {row['p50_ms']} ms, p95 {row['p95_ms']} ms, max {row['max_ms']} ms, "
            f"{row['queries']} queries ({n} requests; the first {row['first_ms']} ms)")
    return rows


class _nothing:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def counts_of():
    from clinic.models import CaptureSession, Comparison, Job, Patient, Reconstruction, Visit

    return {m.__name__: m.objects.count() for m in (Patient, Visit, CaptureSession, Job, Reconstruction, Comparison)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--patients", type=int, default=10000)
    ap.add_argument("--visits", type=int, default=50000)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--seed", type=int, default=28)
    ap.add_argument("--keep", action="store_true", help="keep the database (its name is printed)")
    ap.add_argument("--reuse", metavar="NAME", help="time a database kept by an earlier --keep run")
    ap.add_argument("--json", metavar="OUT", help="write the figures here")
    ap.add_argument("--only", nargs="*", help="time only the pages whose name contains one of these words")
    args = ap.parse_args()
    run = provenance(__file__)
    if args.visits < args.patients:
        ap.error("--visits must be at least --patients")

    dbname = args.reuse or f"torsoscan_bench_pages_{os.getpid()}"
    var = Path(tempfile.gettempdir()) / dbname  # the media (the analysed torsos' pictures) of this database
    if not args.reuse:
        run_sql(f'CREATE DATABASE "{dbname}"')
    var.mkdir(exist_ok=True)
    setup_django(dbname, var)
    from django.core.management import call_command
    from django.db import connections

    keep = args.keep or bool(args.reuse)
    try:
        t = time.perf_counter()
        call_command("migrate", verbosity=0)
        log(f"database {dbname} migrated in {time.perf_counter() - t:.0f} s")
        if not args.reuse:
            seed(args)
        rows_in = counts_of()
        log("rows: " + ", ".join(f"{k} {v}" for k, v in rows_in.items()))
        load_before = os.getloadavg()
        t = time.perf_counter()
        pages = time_pages(args.repeats, args.only)
        load_after = os.getloadavg()
        out = {**run,
               "load_average_1min": {"before": round(load_before[0], 2), "after": round(load_after[0], 2)},
               "timing_s": round(time.perf_counter() - t, 1), "rows": rows_in, "repeats": args.repeats,
               "target_p95_ms": 150, "pages": pages}
        print()
        print(f"{'page':<48} {'n':>4} {'first ms':>9} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8} {'queries':>8}")
        for r in pages:
            mark = "" if r["p95_ms"] <= 150 else "  > 150 ms"
            print(f"{r['page']:<48} {r['requests']:>4} {r['first_ms']:>9.1f} {r['p50_ms']:>8.1f} {r['p95_ms']:>8.1f} "
                  f"{r['max_ms']:>8.1f} {r['queries']:>8}{mark}")
        print(f"load average (1 min) before / after: {load_before[0]:.2f} / {load_after[0]:.2f}")
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps(out, indent=1, ensure_ascii=False) + "\n")
    finally:
        connections.close_all()
        if keep:
            log(f"kept database {dbname} (files in {var}); "
                f"time it again with --reuse {dbname}")
        else:
            run_sql(f'DROP DATABASE IF EXISTS "{dbname}" WITH (FORCE)')
            shutil.rmtree(var, ignore_errors=True)
            log(f"dropped database {dbname}")


if __name__ == "__main__":
    main()
