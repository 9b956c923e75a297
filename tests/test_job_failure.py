"""A job whose engine step raises is marked failed with the error; its capture stays and it can be re-run."""

import json

import pytest
from django.core.files.base import ContentFile

from clinic.models import Calibration, CaptureImage, Job
from tests.api_helpers import auth, image_bytes, open_session, put, small_bundle


def _calibrated(rig):
    cams = {c: {"width": 40, "height": 30, "fx": 80.0, "fy": 80.0, "cx": 20.0, "cy": 15.0, "dist": [0] * 5,
                "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "C": [0, 0, -500.0]} for c in ("A1", "A2", "B1")}
    calib = Calibration.objects.create(rig=rig)
    calib.file.save("c.json", ContentFile(json.dumps({
        "format": "torso-calibration/1", "rig": rig.serial, "calibrated_at": "2026-11-22T08:00:00+00:00",
        "frame": "testfield pose 0", "cameras": cams}).encode()))
    return calib


@pytest.mark.django_db(transaction=True)
def test_an_engine_fault_fails_the_job_keeps_the_capture_and_it_reruns(client, small_rig, alice, tmp_path,
                                                                       monkeypatch):
    import recon_engine.reconstruction as engine

    rig, key = small_rig
    _calibrated(rig)

    def broken(*args, **kwargs):
        raise RuntimeError("simulated engine fault")

    monkeypatch.setattr(engine, "reconstruct_arm", broken)
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    for cam in ("A1", "A2", "B1"):
        put(client, key, sid, cam, image_bytes(folder, cam))
    body = client.post(f"/api/sessions/{sid}/finalize", **auth(key)).json()
    job_id = body["jobs"][0]["id"]
    job = client.get(f"/api/jobs/{job_id}", **auth(key)).json()
    assert job["state"] == "failed"
    assert "simulated engine fault" in job["arms"]["A"]["error"]
    assert "reference arm A" in job["error"] and "simulated engine fault" in job["error"]
    stored = [im.file.name for im in CaptureImage.objects.filter(session__uid=sid)]
    assert len(stored) == 3

    # the fault is fixed: the technician re-runs the job on the kept capture
    calls = []

    def fixed(capture, rig_, calibration, arm, *a, **kw):
        calls.append((arm, sorted(capture.cameras)))
        raise ValueError(f"arm {arm}: too few features in 40 x 30 px")

    monkeypatch.setattr(engine, "reconstruct_arm", fixed)
    client.force_login(alice)
    r = client.post(f"/api/jobs/{job_id}/rerun")
    assert r.status_code == 200
    job = Job.objects.get(uid=job_id)
    assert job.attempt == 2 and sorted(calls) == [("A", ["A1", "A2"]), ("B", ["B1"])]
    assert job.state == "failed" and "too few features" in job.error
    assert [im.file.name for im in CaptureImage.objects.filter(session__uid=sid)] == stored


@pytest.mark.django_db(transaction=True)
def test_a_task_delivered_twice_does_the_work_once(small_rig):
    from clinic import pipeline

    rig, _ = small_rig
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, state=Job.QUEUED)
    assert pipeline.start_reconstruction(job.pk) == []  # claimed, then failed: no calibration
    job.refresh_from_db()
    assert job.state == "failed" and job.attempt == 1
    assert pipeline.start_reconstruction(job.pk) == [] and Job.objects.get(pk=job.pk).attempt == 1
