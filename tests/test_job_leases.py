"""A claim holds a lease: a redelivered step whose lease lapsed (its worker died) takes the work over and the job
completes; a step whose lease is live is refused; a job stuck running is re-run once nothing holds it.

The embedded default (jobs in-process) with the simulator's tiny rig; the
stuck states are what a worker killed mid-step leaves in the rows.
"""

from datetime import timedelta

import pytest
from django.core.files.base import ContentFile
from django.core.files.storage import default_storage
from django.utils import timezone

from clinic import filecheck, pipeline, tasks
from clinic.models import ArmTask, Calibration, CaptureSession, Job, Reconstruction, Rig
from tests.service_flow import ClientApi, calibrate_set, finalized_without_its_job, register_rig, upload_capture


def _api(client):
    api = ClientApi(client)
    api.login("alice", "pw-alice")
    return api


def _ago(seconds):
    return timezone.now() - timedelta(seconds=seconds)


@pytest.mark.django_db(transaction=True)
def test_it_reruns_a_job_stuck_running_only_once_its_lease_lapsed(client, alice, clinic, rig_session_1):
    api = _api(client)
    key = register_rig(api, clinic.pk, rig_session_1)
    # the set's poses, uploaded as a set of four: incomplete, so no job starts by itself
    for folder in sorted((rig_session_1 / "captures").glob("testfield-pose*")):
        upload_capture(api, key, folder, calibration_set="s", poses=4)
    rig = Rig.objects.get()
    # what a worker killed during the bundle adjustment leaves: running, claimed, its lease renewed until now
    job = Job.objects.create(kind=Job.CALIBRATION, rig=rig, session=CaptureSession.objects.first(),
                             state=Job.RUNNING, stage="bundle adjustment", percent=20, attempt=1,
                             claimed=_ago(600), started=_ago(600), lease_until=timezone.now() + timedelta(seconds=60))
    job.sessions.set(CaptureSession.objects.all())

    r = client.post(f"/api/jobs/{job.uid}/rerun")
    assert r.status_code == 409 and "running and its worker is alive" in r.json()["detail"]
    assert tasks.run_calibration.delay(job.pk).get() == "not claimed"  # a redelivery is refused too
    assert Job.objects.get(pk=job.pk).attempt == 1

    Job.objects.filter(pk=job.pk).update(lease_until=_ago(1))  # the worker is gone: its lease lapses
    r = client.post(f"/api/jobs/{job.uid}/rerun")
    assert r.status_code == 200, r.content
    job.refresh_from_db()
    assert (job.state, job.attempt, job.lease_until) == (Job.SUCCEEDED, 2, None)
    assert Calibration.objects.get().job_id == job.pk


@pytest.mark.django_db(transaction=True)
def test_it_hands_a_lapsed_arm_to_its_redelivery_and_refuses_a_live_one(client, alice, clinic, rig_session_1):
    api = _api(client)
    key = register_rig(api, clinic.pk, rig_session_1)
    assert calibrate_set(api, key, rig_session_1, "s")["state"] == "succeeded"
    # the torso's images, uploaded and marked finalized without running its job (in-process it would run at once)
    session = finalized_without_its_job(api, key, rig_session_1 / "captures" / "visit0-a")
    rig = Rig.objects.get()
    # a reconstruction in its arms: A's worker was killed (lease lapsed), B's is alive, C and D wait
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, calibration=rig.current_calibration,
                             state=Job.RUNNING, stage="arms", percent=5, attempt=1, claimed=_ago(300),
                             started=_ago(300), dispatched=_ago(300))
    ArmTask.objects.create(job=job, arm="A", state=Job.RUNNING, claimed=_ago(200), lease_until=_ago(5),
                           dispatched=_ago(300))
    ArmTask.objects.create(job=job, arm="B", state=Job.RUNNING, claimed=_ago(10),
                           lease_until=timezone.now() + timedelta(seconds=60), dispatched=_ago(300))
    for arm in "CD":
        ArmTask.objects.create(job=job, arm=arm, dispatched=_ago(300))

    assert tasks.reconstruct_arm.delay(job.pk, "A").get() == "arm done"  # A's redelivery takes it over
    assert tasks.reconstruct_arm.delay(job.pk, "B").get() == "not claimed"  # B's is refused: its worker is alive
    assert ArmTask.objects.get(job=job, arm="A").state == Job.SUCCEEDED
    assert ArmTask.objects.get(job=job, arm="B").state == Job.RUNNING

    # the sweeper sends what waits (C, D), not B
    assert pipeline.redispatch_stalled(older_than=0) == [("clinic.tasks.reconstruct_arm", job.pk, "C"),
                                                          ("clinic.tasks.reconstruct_arm", job.pk, "D")]
    assert Job.objects.get(pk=job.pk).stage == "arms"
    # B's worker dies: once its lease lapses the sweeper sends B, and the last arm hands over to the registration
    ArmTask.objects.filter(job=job, arm="B").update(lease_until=_ago(1))
    assert pipeline.redispatch_stalled(older_than=0) == [("clinic.tasks.reconstruct_arm", job.pk, "B")]
    job.refresh_from_db()
    assert (job.state, job.stage, job.attempt) == (Job.SUCCEEDED, "done", 1), job.error
    assert set(job.arms.values_list("state", flat=True)) == {Job.SUCCEEDED}
    assert Reconstruction.objects.get(job=job).status in ("ok", "partial")

    # a registration whose worker died half-way (its torso already stored): once its lease lapses, the sweeper
    # has it done again, and the half-made result is replaced
    half_made = Reconstruction.objects.get(job=job)
    # and files it stored before a row named them: a picture of the analysis, a comparison's deformation map
    strays = [default_storage.save(f"results/{job.uid}/pictures/back.png", ContentFile(b"half a picture")),
              default_storage.save(f"comparisons/1-{half_made.pk}-deformation.ply", ContentFile(b"ply"))]
    Job.objects.filter(pk=job.pk).update(state=Job.RUNNING, stage="indices and pictures", finished=None,
                                         claimed=_ago(60), lease_until=_ago(1), dispatched=_ago(60))
    assert pipeline.redispatch_stalled(older_than=0) == [("clinic.tasks.register", job.pk)]
    job.refresh_from_db()
    assert (job.state, job.stage) == (Job.SUCCEEDED, "done"), job.error
    assert Reconstruction.objects.get(job=job).pk != half_made.pk
    # one torso's files (the new attempt's, under the same names), and no stored file that no row names
    assert not [name for name in strays if default_storage.exists(name)]
    rec = Reconstruction.objects.get(job=job)
    assert sorted(filecheck.stored_names(default_storage, f"results/{job.uid}")) == sorted(
        [rec.torso.name, rec.mesh.name, rec.report_file.name, *rec.pictures.values(),
         *(arm.surface.name for arm in job.arms.all())])
    report = filecheck.check(grace=timedelta(0))
    assert (report.orphans, report.missing) == ([], [])
