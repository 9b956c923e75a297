"""Re-running a finished scan makes its torso anew: a technician may not discard a clinician's landmark
corrections that way (technicians may not correct landmarks either); an administrator may."""
import pytest

from clinic.models import Reconstruction
from tests.patient_records import patient_with_records


@pytest.fixture
def corrected(clinic, monkeypatch):
    import clinic.pipeline as pipeline

    monkeypatch.setattr(pipeline, "send", lambda *a: True)  # the re-run is only queued
    _, recs, _ = patient_with_records(clinic)
    Reconstruction.objects.filter(pk=recs[1].pk).update(
        landmarks={"sacral_point": [1.0, 2.0, 3.0]}, landmark_history=[{"landmarks": None, "by": "charlie"}])
    return recs[1]


@pytest.mark.django_db
def test_it_refuses_a_technicians_rerun_of_a_corrected_scan(client, alice, corrected):
    client.force_login(alice)
    r = client.post(f"/api/jobs/{corrected.job.uid}/rerun")
    assert r.status_code == 403 and "corrected" in r.json()["detail"]
    assert Reconstruction.objects.get(pk=corrected.pk).landmarks == {"sacral_point": [1.0, 2.0, 3.0]}


@pytest.mark.django_db
def test_an_administrator_may_rerun_it(client, ada, corrected):
    client.force_login(ada)
    assert client.post(f"/api/jobs/{corrected.job.uid}/rerun").status_code == 200
    assert not Reconstruction.objects.filter(pk=corrected.pk).exists()


@pytest.mark.django_db
def test_a_technician_may_rerun_a_scan_nobody_corrected(client, alice, clinic, monkeypatch):
    import clinic.pipeline as pipeline

    monkeypatch.setattr(pipeline, "send", lambda *a: True)
    _, recs, _ = patient_with_records(clinic)
    client.force_login(alice)
    assert client.post(f"/api/jobs/{recs[1].job.uid}/rerun").status_code == 200
