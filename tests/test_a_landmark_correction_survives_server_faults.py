"""A clinician's landmark correction is never lost to a fault of the server.

Only the analysis refusing the landmarks undoes a correction; a full disk does not, and neither does a job that
fails while a newer correction arrives. The correction and its job commit together.
"""
import errno

import pytest
from django.core.files.storage import FileSystemStorage
from django.db import OperationalError
from django.test import Client

from clinic import pipeline
from clinic.models import Job, Reconstruction
from tests.patient_records import correct_sacral_point
from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_a_full_disk_keeps_the_correction_and_says_so(client, charlie, patient_with_two_visits,  # noqa: F811
                                                      monkeypatch, django_capture_on_commit_callbacks):
    visit = patient_with_two_visits.visits.first()
    real_save = FileSystemStorage._save

    def full_disk(self, name, content):
        if "pictures/" in name:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_save(self, name, content)

    monkeypatch.setattr(FileSystemStorage, "_save", full_disk)
    rec, _, moved, r = correct_sacral_point(client, charlie, visit)
    assert r.status_code == 302
    job = Job.objects.get(kind=Job.LANDMARKS)
    rec.refresh_from_db()
    assert job.state == Job.FAILED and "the correction is kept" in job.error
    assert rec.landmarks == {"sacral_point": moved}
    monkeypatch.undo()  # the disk mended: the clinician runs the job again, which applies the kept correction
    page = client.get(f"/visits/{visit.pk}/").content.decode()
    assert "the correction is kept" in page and f"/jobs/{job.uid}/rerun" in page
    with django_capture_on_commit_callbacks(execute=True):
        client.post(f"/jobs/{job.uid}/rerun")
    job.refresh_from_db()
    rec.refresh_from_db()
    assert job.state == Job.SUCCEEDED
    assert rec.indices["landmarks"]["sacral_point"]["source"] != "auto"
    assert rec.indices["landmarks"]["sacral_point"]["position_mm"] == pytest.approx(moved, abs=3.0)


@pytest.mark.django_db(transaction=True)
def test_a_correction_is_not_stored_without_its_job(charlie, patient_with_two_visits, monkeypatch):  # noqa: F811
    visit = patient_with_two_visits.visits.first()
    real_create = Job.objects.create

    def lost(**kw):
        if kw.get("kind") == Job.LANDMARKS:
            raise OperationalError("server closed the connection unexpectedly")
        return real_create(**kw)

    monkeypatch.setattr(Job.objects, "create", lost)
    rec, auto, _, r = correct_sacral_point(Client(raise_request_exception=False), charlie, visit)
    assert r.status_code >= 500
    rec.refresh_from_db()
    assert rec.landmarks is None and not rec.landmark_history  # nothing half-applied: the clinician tries again


@pytest.mark.django_db
def test_a_failing_job_leaves_a_newer_correction_alone(patient_with_two_visits, monkeypatch):  # noqa: F811
    import analysis.pictures

    rec = Reconstruction.objects.filter(session__visit__patient=patient_with_two_visits).first()
    first, second = {"sacral_point": [1.0, 2.0, 3.0]}, {"sacral_point": [4.0, 5.0, 6.0]}
    Reconstruction.objects.filter(pk=rec.pk).update(landmarks=first, landmark_history=[{"landmarks": None, "by": "a"}])
    job = Job.objects.create(kind=Job.LANDMARKS, rig_id=rec.session.rig_id, session_id=rec.session_id, later=rec)

    def refuse(*a, **kw):
        raise ValueError("the first correction's landmarks give no frame")

    def second_correction_lands(*a, **kw):
        # the clinician's second correction commits after the analysis failed, before the job undoes the first
        Reconstruction.objects.filter(pk=rec.pk).update(
            landmarks=second, landmark_history=[{"landmarks": None, "by": "a"}, {"landmarks": first, "by": "b"}])

    monkeypatch.setattr(analysis.pictures, "torso_pictures", refuse)
    monkeypatch.setattr(pipeline.log, "exception", second_correction_lands)
    assert pipeline.run_landmark_analysis(job.pk) == "failed"
    rec.refresh_from_db()
    assert rec.landmarks == second and len(rec.landmark_history) == 2
    assert "were not used" in Job.objects.get(pk=job.pk).error
