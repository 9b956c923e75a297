"""A registration whose worker was slowed past its lease (a loaded machine) while a redelivery took it over: the
slow one stores no torso, and the job completes with one (CI, 2026-12-07: the slow worker's torso was stored
first and the redelivery's insert failed the whole job on the unique job)."""

from datetime import timedelta

import pytest
from django.utils import timezone

from clinic import filecheck, pipeline, tasks
from clinic.models import ArmTask, Job, Reconstruction, Rig
from tests.service_flow import ClientApi, calibrate_set, finalized_without_its_job, register_rig


@pytest.mark.django_db(transaction=True)
def test_a_registration_that_lost_its_claim_stores_no_torso(client, alice, clinic, rig_session_1, monkeypatch):
    import recon_engine.reconstruction as engine

    api = ClientApi(client)
    api.login("alice", "pw-alice")
    key = register_rig(api, clinic.pk, rig_session_1)
    assert calibrate_set(api, key, rig_session_1, "s")["state"] == "succeeded"
    session = finalized_without_its_job(api, key, rig_session_1 / "captures" / "visit0-a")
    rig = Rig.objects.get()
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, calibration=rig.current_calibration,
                             state=Job.RUNNING, stage="arms", percent=5, attempt=1, claimed=timezone.now(),
                             started=timezone.now(), dispatched=timezone.now())
    for arm in "ABCD":
        ArmTask.objects.create(job=job, arm=arm, dispatched=timezone.now())

    real = engine.register_arms
    redelivery = {}

    def slowed(*args, **kwargs):
        result = real(*args, **kwargs)
        # meanwhile the sweeper found this worker's lease lapsed and a redelivery claimed the registration
        redelivery["claim"] = timezone.now()
        Job.objects.filter(pk=job.pk).update(claimed=redelivery["claim"], lease_until=timezone.now())
        return result

    monkeypatch.setattr(engine, "register_arms", slowed)
    for arm in "ABC":
        assert tasks.reconstruct_arm.delay(job.pk, arm).get() == "arm done"
    tasks.reconstruct_arm.delay(job.pk, "D").get()  # the last arm hands over to the registration, in-process
    assert "claim" in redelivery
    job.refresh_from_db()
    assert (job.state, job.claimed) == (Job.RUNNING, redelivery["claim"])  # not failed, still the redelivery's
    assert not Reconstruction.objects.filter(job=job).exists()  # the slow worker stored no torso
    surfaces = sorted(arm.surface.name for arm in job.arms.all())
    assert sorted(filecheck.stored_names(pipeline.default_storage, f"results/{job.uid}")) == surfaces

    # the redelivery (its worker, too, found lapsed here) completes the job with one torso
    monkeypatch.setattr(engine, "register_arms", real)
    Job.objects.filter(pk=job.pk).update(lease_until=timezone.now() - timedelta(seconds=1))
    assert pipeline.redispatch_stalled(older_than=0) == [("clinic.tasks.register", job.pk)]
    job.refresh_from_db()
    assert (job.state, job.stage) == (Job.SUCCEEDED, "done"), job.error
    rec = Reconstruction.objects.get(job=job)
    assert sorted(filecheck.stored_names(pipeline.default_storage, f"results/{job.uid}")) == sorted(
        [rec.torso.name, rec.mesh.name, rec.report_file.name, *rec.pictures.values(), *surfaces])
