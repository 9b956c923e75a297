"""Re-running a job: the page allows exactly whom the API allows (not clinicians; administrators, technicians)."""

import pytest

from clinic.models import CaptureSession, Job


@pytest.fixture
def failed_job(small_rig):
    rig, _ = small_rig
    s = CaptureSession.objects.create(rig=rig, kind="torso", manifest={"images": []}, manifest_sha256="0",
                                      idempotency_key="k", captured_at="2026-11-22")
    return Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=s, state=Job.FAILED, error="boom")


def _state(job):
    job.refresh_from_db()
    return job.state


@pytest.mark.django_db
def test_it_refuses_a_clinician_on_the_page_and_in_the_api(client, charlie, failed_job):
    client.force_login(charlie)
    r = client.post(f"/jobs/{failed_job.uid}/rerun")
    assert r.status_code == 403 and b"clinician cannot do this" in r.content
    assert client.post(f"/api/jobs/{failed_job.uid}/rerun").status_code == 403
    assert _state(failed_job) == Job.FAILED


@pytest.mark.django_db
def test_it_hides_the_button_from_a_clinician(client, charlie, ada, failed_job):
    from clinic.models import Patient, Visit

    visit = Visit.objects.create(patient=Patient.objects.create(clinic=failed_job.rig.clinic, identifier="P-1",
                                                                name="Pat"))
    CaptureSession.objects.filter(pk=failed_job.session_id).update(visit=visit)
    client.force_login(charlie)
    assert b"Re-run" not in client.get(f"/visits/{visit.pk}/").content
    client.force_login(ada)
    assert b"Re-run" in client.get(f"/visits/{visit.pk}/").content


@pytest.mark.django_db
@pytest.mark.parametrize("who", ["ada", "alice"])
def test_it_lets_an_administrator_or_technician_rerun_from_the_page_and_the_api(client, request, who, failed_job):
    client.force_login(request.getfixturevalue(who))
    assert client.post(f"/jobs/{failed_job.uid}/rerun").status_code == 302
    assert _state(failed_job) == Job.QUEUED
    Job.objects.filter(pk=failed_job.pk).update(state=Job.FAILED)
    assert client.post(f"/api/jobs/{failed_job.uid}/rerun").status_code == 200
    assert _state(failed_job) == Job.QUEUED


@pytest.mark.django_db
def test_it_answers_409_on_the_page_for_a_job_that_cannot_be_rerun(client, ada, failed_job):
    Job.objects.filter(pk=failed_job.pk).update(state=Job.RUNNING, lease_until="2999-01-01T00:00:00Z")
    client.force_login(ada)
    r = client.post(f"/jobs/{failed_job.uid}/rerun")
    assert r.status_code == 409 and b"its worker is alive" in r.content
