"""A reconstruction that succeeded is the patient's torso: re-running it would delete it, the landmarks a clinician
corrected on it and its comparisons before a new torso exists (a re-run that then failed left the patient with
none). It is refused, for every role; a failed one is re-run as before."""
import pytest

from clinic.models import Comparison, Job, Reconstruction
from tests.patient_records import patient_with_records


@pytest.mark.django_db
@pytest.mark.parametrize("who", ["ada", "alice"])
def test_it_refuses_to_rerun_a_finished_scan(client, request, who, clinic, monkeypatch):
    import clinic.pipeline as pipeline

    monkeypatch.setattr(pipeline, "send", lambda *a: True)
    _, recs, _ = patient_with_records(clinic)
    Reconstruction.objects.filter(pk=recs[1].pk).update(landmarks={"sacral_point": [1.0, 2.0, 3.0]},
                                                        landmark_history=[{"landmarks": None, "by": "charlie"}])
    client.force_login(request.getfixturevalue(who))
    r = client.post(f"/api/jobs/{recs[1].job.uid}/rerun")
    assert r.status_code == 409 and "succeeded" in r.json()["detail"]
    assert Reconstruction.objects.get(pk=recs[1].pk).landmarks == {"sacral_point": [1.0, 2.0, 3.0]}
    assert Comparison.objects.count() == 1 and Job.objects.get(pk=recs[1].job.pk).state == Job.SUCCEEDED
