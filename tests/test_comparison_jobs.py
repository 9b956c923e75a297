"""A comparison is computed by a job, not inside the page's request: the page shows its progress, then the
result. The same comparison asked for twice at once makes one job and one result (no duplicate row or file,
no 500).

The analysis's heavy calls (registration, pictures) are replaced by quick stand-ins that write the same files,
so what is tested is the service around them: the job, its claim, the storing and the pages.
"""

import json
import threading
from datetime import timedelta
from pathlib import Path

import pytest
from django.core.files.storage import default_storage
from django.db import connection
from django.test import Client
from django.utils import timezone

from clinic import pipeline, tasks
from clinic.models import Comparison, Job
from tests.patient_records import two_torsos

REPORT = {"average_normal_distance_mm": 0.4, "matched_fraction": 0.93, "regions": {},
          "signed_distance_mm": {"mean": 0.1, "p05": -0.5, "p95": 0.6}}


@pytest.fixture
def quick_analysis(monkeypatch):
    """Stand-ins for the registration and the pictures; ``calls`` counts the comparisons computed, and
    ``meet`` (a barrier, when set) holds each computation until another is under way too."""
    import analysis.compare
    import analysis.pictures
    import analysis.torso

    state = {"calls": 0, "meet": None}

    def compare_torsos(earlier, later, **kw):
        state["calls"] += 1
        if state["meet"] is not None:
            state["meet"].wait(timeout=10)
        return dict(REPORT)

    def write_comparison(out, result):
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "report.json").write_text(json.dumps(result))
        (Path(out) / "deformation.ply").write_bytes(b"ply deformation")

    def comparison_pictures(out, dest, mdc_mm=None):
        Path(dest).mkdir(parents=True, exist_ok=True)
        (Path(dest) / "deformation.png").write_bytes(b"\x89PNG deformation")
        return {"deformation": Path(dest) / "deformation.png"}

    monkeypatch.setattr(analysis.torso, "read_torso", lambda path: str(path))
    monkeypatch.setattr(analysis.compare, "compare_torsos", compare_torsos)
    monkeypatch.setattr(analysis.compare, "write_comparison", write_comparison)
    monkeypatch.setattr(analysis.pictures, "comparison_pictures", comparison_pictures)
    return state


@pytest.fixture
def two_scans(clinic):
    """A patient with two visits, a good torso each; ``(patient, earlier, later)``."""
    patient, (earlier, later) = two_torsos(clinic, "RIG-J", "P-J", "Jo Queue")
    return patient, earlier, later


def _url(patient, earlier, later):
    return f"/patients/{patient.pk}/compare/?earlier_scan={earlier.pk}&later_scan={later.pk}"


def _stored_comparison_files():
    folders, files = default_storage.listdir("comparisons") if default_storage.exists("comparisons") else ([], [])
    return {f"comparisons/{f}" for f in files} | {f"comparisons/{d}/{f}" for d in folders
                                                  for f in default_storage.listdir(f"comparisons/{d}")[1]}


def _referenced(comparison):
    return {comparison.deformation.name, *comparison.pictures.values()}


@pytest.mark.django_db
def test_the_page_queues_a_job_shows_its_progress_then_the_result(client, charlie, two_scans, quick_analysis,
                                                                     monkeypatch):
    patient, earlier, later = two_scans
    sent = []
    monkeypatch.setattr(pipeline, "send", lambda task, *args: sent.append((task.name, *args)) or True)
    client.force_login(charlie)

    # a GET (a followed link, a prefetch) starts nothing: the page offers to compare
    r = client.get(_url(patient, earlier, later))
    html = r.content.decode()
    assert r.status_code == 200 and "have not been compared yet" in html and 'http-equiv="refresh"' not in html
    assert not Job.objects.filter(kind=Job.COMPARISON).exists() and sent == []
    # the patient page's form posts the two scans: the job is made, and the answer leads to the pair's page
    r = client.post(f"/patients/{patient.pk}/compare/", {"earlier_scan": earlier.pk, "later_scan": later.pk})
    assert r.status_code == 302 and r["Location"] == _url(patient, earlier, later)
    r = client.get(r["Location"])
    assert r.status_code == 200
    html = r.content.decode()
    job = Job.objects.get(kind=Job.COMPARISON)
    assert (job.earlier, job.later, job.state, job.session) == (earlier, later, Job.QUEUED, later.session)
    assert sent == [(tasks.run_comparison.name, job.pk)]
    assert 'http-equiv="refresh"' in html and "waiting for a worker" in html and "Jo Queue" in html
    assert quick_analysis["calls"] == 0 and not Comparison.objects.exists()  # nothing computed in the request

    # a refresh while it waits: the same job, not sent again
    assert client.get(_url(patient, earlier, later)).status_code == 200
    assert Job.objects.filter(kind=Job.COMPARISON).count() == 1 and len(sent) == 1

    # a worker takes it: the page says what it does
    Job.objects.filter(pk=job.pk).update(state=Job.RUNNING, stage="lining up the two torsos", percent=10)
    html = client.get(_url(patient, earlier, later)).content.decode()
    assert "lining up the two torsos" in html and 'value="10"' in html

    Job.objects.filter(pk=job.pk).update(state=Job.QUEUED)
    assert tasks.run_comparison.delay(job.pk).get() == "succeeded"
    assert tasks.run_comparison.delay(job.pk).get() == "not claimed"  # a second delivery does nothing
    r = client.get(_url(patient, earlier, later))
    html = r.content.decode()
    assert r.status_code == 200 and 'id="deformation"' in html and 'http-equiv="refresh"' not in html
    assert quick_analysis["calls"] == 1 and Comparison.objects.count() == 1
    # the visit page's jobs are those that made its scan (the comparison is the comparison page's)
    assert [j.kind for j in client.get(f"/visits/{later.session.visit_id}/").context["jobs"]] == [Job.RECONSTRUCTION]


@pytest.mark.django_db
def test_a_failed_comparison_says_why_and_can_be_tried_again(client, charlie, two_scans, quick_analysis,
                                                            monkeypatch, django_capture_on_commit_callbacks):
    import analysis.compare

    patient, earlier, later = two_scans
    client.force_login(charlie)
    monkeypatch.setattr(analysis.compare, "compare_torsos",
                        lambda *a, **kw: (_ for _ in ()).throw(ValueError("the torsos barely overlap")))
    r = client.post(_url(patient, earlier, later))  # eager: the job runs in-process, and fails
    assert r.status_code == 302
    r = client.get(r["Location"])
    html = r.content.decode()
    assert r.status_code == 200 and "The torsos barely overlap" in html and "Try again" in html
    assert 'http-equiv="refresh"' not in html  # nothing to wait for
    assert Job.objects.get(kind=Job.COMPARISON).state == Job.FAILED
    assert client.get(_url(patient, earlier, later)).status_code == 200  # a mere refresh does not re-run it
    assert Job.objects.get(kind=Job.COMPARISON).attempt == 1

    monkeypatch.setattr(analysis.compare, "compare_torsos", lambda *a, **kw: dict(REPORT))  # now it works
    with django_capture_on_commit_callbacks(execute=True):  # the re-run is sent once its row is committed
        r = client.post(_url(patient, earlier, later))
    assert r.status_code == 302 and r["Location"] == _url(patient, earlier, later)
    job = Job.objects.get(kind=Job.COMPARISON)
    assert (job.state, job.attempt) == (Job.SUCCEEDED, 2)
    assert 'id="deformation"' in client.get(r["Location"]).content.decode()


@pytest.mark.django_db
def test_another_clinic_cannot_start_or_see_a_comparison(client, olga, two_scans, quick_analysis):
    patient, earlier, later = two_scans
    client.force_login(olga)
    assert client.get(_url(patient, earlier, later)).status_code == 404
    assert client.post(_url(patient, earlier, later)).status_code == 404
    assert not Job.objects.filter(kind=Job.COMPARISON).exists()


def _in_threads(n, work):
    """``work(k)`` in ``n`` threads started together; their results (or exceptions)."""
    out = [None] * n

    def run(k):
        try:
            out[k] = work(k)
        except Exception as exc:  # reported by the test, not lost in the thread
            out[k] = exc
        finally:
            connection.close()

    threads = [threading.Thread(target=run, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    return out


@pytest.mark.django_db(transaction=True)
def test_the_same_comparison_asked_twice_at_once_makes_one_job_and_one_result(charlie, two_scans, quick_analysis,
                                                                              monkeypatch):
    patient, earlier, later = two_scans
    # both requests find no job, then both create one: one insert wins, the other takes the winner's job
    both_checked = threading.Barrier(2)
    job_of = pipeline.comparison_job_of

    def check_together(*args):
        found = job_of(*args)
        both_checked.wait(timeout=10)
        return found

    monkeypatch.setattr(pipeline, "comparison_job_of", check_together)

    def ask(k):
        c = Client()
        c.force_login(charlie)
        return c.post(_url(patient, earlier, later))

    answers = _in_threads(2, ask)
    assert all(getattr(r, "status_code", r) == 302 for r in answers), answers
    assert not both_checked.broken
    assert Job.objects.filter(kind=Job.COMPARISON).count() == 1
    assert Job.objects.get(kind=Job.COMPARISON).state == Job.SUCCEEDED
    assert quick_analysis["calls"] == 1
    comparison = Comparison.objects.get()
    assert _stored_comparison_files() == _referenced(comparison)


@pytest.mark.django_db(transaction=True)
def test_two_computations_of_one_pair_store_one_result_and_no_stray_file(two_scans, quick_analysis):
    from clinic.analysis_step import compare_reconstructions

    _, earlier, later = two_scans
    # a page's job and a registration comparing the same pair at once: both compute, one result is kept
    quick_analysis["meet"] = threading.Barrier(2)
    results = _in_threads(2, lambda k: compare_reconstructions(earlier, later).pk)
    assert quick_analysis["calls"] == 2 and not quick_analysis["meet"].broken
    assert results[0] == results[1] == Comparison.objects.get().pk, results
    assert _stored_comparison_files() == _referenced(Comparison.objects.get())


@pytest.mark.django_db
def test_a_comparison_job_the_broker_lost_is_sent_again(two_scans, monkeypatch):
    _, earlier, later = two_scans
    sent = []
    monkeypatch.setattr(pipeline, "send", lambda task, *args: sent.append((task.name, *args)) or True)
    job = pipeline.request_comparison(earlier, later)
    Job.objects.filter(pk=job.pk).update(dispatched=timezone.now() - timedelta(hours=1))
    assert pipeline.redispatch_stalled() == [(tasks.run_comparison.name, job.pk)]
    # its worker died while comparing: once its lease lapsed, it is sent again
    now = timezone.now()
    Job.objects.filter(pk=job.pk).update(state=Job.RUNNING, claimed=now - timedelta(seconds=200),
                                         dispatched=now - timedelta(seconds=10), lease_until=now - timedelta(seconds=1))
    assert pipeline.redispatch_stalled() == [(tasks.run_comparison.name, job.pk)]
