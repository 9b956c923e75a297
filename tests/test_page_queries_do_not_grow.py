"""A page asks the database as many times for a long history as for a short one: its queries do not grow with the
number of patients, visits, scans, comparisons or calibrations (the figures at 10 000 patients and 50 000 visits:
benchmarks/bench_pages.py, docs/benchmarks.md)."""

import datetime as dt
from itertools import count

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.utils import timezone

from clinic.models import (Calibration, Camera, CaptureSession, Comparison, Job, Patient, Reconstruction, Rig,
                           StabilityCheck, Visit)

_serial = count(1)
REPORT = {"average_normal_distance_mm": 0.4, "matched_fraction": 0.95,
          "signed_distance_mm": {"mean": 0.1, "p05": -0.6, "p95": 0.7}, "facing": {"consistent": True}}


def _queries(client, url) -> int:
    client.get(url)  # the first request fills what is cached (the clinic's noise figures, a chart)
    with CaptureQueriesContext(connection) as queries:
        response = client.get(url)
    assert response.status_code == 200, url
    return len(queries)


def _scan(rig, visit, rotation):
    k = next(_serial)
    session = CaptureSession.objects.create(rig=rig, kind="torso", visit=visit, manifest={}, manifest_sha256=str(k),
                                            idempotency_key=str(k), captured_at=str(visit.date),
                                            state=CaptureSession.FINALIZED)
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED, percent=100)
    return Reconstruction.objects.create(job=job, session=session, status="ok", points=1, report={},
                                         indices={"surface_rotation_deg": {"max": rotation}, "hump_mm": rotation})


def _visits(patient, rig, n, start):
    """``n`` visits four months apart from ``start``, each scanned, each compared with the earlier ones (as the
    pipeline does); the first scanned twice (a repeat pair)."""
    recs = list(Reconstruction.objects.filter(session__visit__patient=patient))
    for k in range(n):
        visit = Visit.objects.create(patient=patient, date=start + dt.timedelta(days=120 * k), reason="follow-up")
        later = _scan(rig, visit, 5.0 + k)
        if k == 0:
            again = _scan(rig, visit, 5.1)
            Comparison.objects.create(earlier=later, later=again, report=REPORT)
        for earlier in recs:
            Comparison.objects.create(earlier=earlier, later=later, report=REPORT)
        recs.append(later)
    return visit


@pytest.fixture
def rig(clinic):
    return Rig.objects.create(clinic=clinic, serial="RIG-Q", description={})


@pytest.mark.django_db
def test_it_shows_a_patients_history_visit_and_comparison_in_as_many_queries_for_eight_visits_as_for_three(
        client, charlie, clinic, rig):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Quinn Query")
    start = timezone.localdate() - dt.timedelta(days=1200)
    last = _visits(p, rig, 3, start)  # three: the headline has both its verdicts
    client.force_login(charlie)

    def urls():
        recs = list(Reconstruction.objects.filter(session__visit__patient=p).order_by("session__visit__date", "pk"))
        return [f"/patients/{p.pk}/", f"/visits/{last.pk}/",
                f"/patients/{p.pk}/compare/?earlier_scan={recs[0].pk}&later_scan={recs[-1].pk}"]

    few = [_queries(client, url) for url in urls()]
    last = _visits(p, rig, 5, start + dt.timedelta(days=400))
    many = [_queries(client, url) for url in urls()]
    assert Visit.objects.filter(patient=p).count() == 8
    assert many == few


@pytest.mark.django_db
def test_it_shows_the_worklist_and_patient_list_in_as_many_queries_for_sixty_patients_as_for_three(
        client, charlie, clinic, rig):
    today = timezone.localdate()

    def patients(n):
        for _ in range(n):
            k = next(_serial)
            p = Patient.objects.create(clinic=clinic, identifier=f"Q-{k}", name=f"Patient {k}")
            Visit.objects.create(patient=p, date=today - dt.timedelta(days=400))  # overdue
            _scan(rig, Visit.objects.create(patient=p, date=today), 5.0)  # today's, scanned

    client.force_login(charlie)
    patients(3)
    few = [_queries(client, url) for url in ("/", "/?q=Patient")]
    patients(57)  # more than a page of the list
    many = [_queries(client, url) for url in ("/", "/?q=Patient", "/?page=2")]
    assert many[:2] == few and many[2] == few[0]


@pytest.mark.django_db
def test_it_shows_a_rig_and_its_stability_chart_in_as_many_queries_for_six_calibrations_as_for_two(
        client, ada, clinic, rig):
    cams = [Camera.objects.create(rig=rig, name=f"A{k}", arm="A", position=k, width=64, height=48,
                                  pixel_size_mm=0.005, nominal_focal_mm=8.0) for k in range(3)]

    def calibrations(n):
        for _ in range(n):
            before = Calibration.objects.filter(rig=rig).first()
            cal = Calibration.objects.create(rig=rig, file="c.json", figures={"sigma0": 1.0},
                                             calibrated_at=timezone.now())
            if before is not None:
                for cam in cams:
                    StabilityCheck.objects.create(camera=cam, calibration=cal, reference=before, zrot_px=0.1,
                                                  rot_px=0.2, spr_px=0.3, arm_px=0.4, threshold_px=1.0, stable=True)

    client.force_login(ada)
    calibrations(2)
    urls = (f"/rigs/{rig.serial}/", f"/rigs/{rig.serial}/stability.svg")
    few = [_queries(client, url) for url in urls]
    calibrations(4)
    many = [_queries(client, url) for url in urls]
    assert StabilityCheck.objects.filter(camera__rig=rig).count() == 15
    assert many == few
