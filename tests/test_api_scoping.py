"""Staff see their own clinic's sessions and jobs only; everything else is a 404."""

import pytest

from clinic.models import CaptureSession, Job


@pytest.mark.django_db
def test_staff_of_other_clinics_get_404(client, small_rig, alice, olga, nobody):
    rig, _ = small_rig
    s = CaptureSession.objects.create(rig=rig, kind="torso", manifest={"images": []}, manifest_sha256="0",
                                      idempotency_key="k", captured_at="2026-11-22")
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=s, state=Job.FAILED)
    client.force_login(alice)
    assert client.get(f"/api/jobs/{job.uid}").status_code == 200
    assert client.get(f"/api/sessions/{s.uid}").status_code == 200
    for user in (olga, nobody):
        client.force_login(user)
        assert client.get(f"/api/jobs/{job.uid}").status_code == 404
        assert client.get(f"/api/sessions/{s.uid}").status_code == 404
        assert client.post(f"/api/jobs/{job.uid}/rerun").status_code == 404
    client.logout()
    assert client.get(f"/api/jobs/{job.uid}").status_code == 401
