"""A landmark correction is checked whole before anything is stored, and is stored with its indices or not at all."""

import pytest
from django.core.files.base import ContentFile


@pytest.fixture
def visit_with_torso(clinic):
    from clinic.models import CaptureSession, Job, Patient, Reconstruction, Rig, Visit

    rig = Rig.objects.create(clinic=clinic, serial="RIG-L", description={})
    visit = Visit.objects.create(patient=Patient.objects.create(clinic=clinic, identifier="P-9", name="Sam"))
    session = CaptureSession.objects.create(rig=rig, kind="torso", visit=visit, manifest={"images": []},
                                            manifest_sha256="0", idempotency_key="0", captured_at="2026-01-01",
                                            state=CaptureSession.FINALIZED)
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED)
    rec = Reconstruction(job=job, session=session, status="ok", points=1, report={}, indices={"landmarks": {}},
                         landmarks={"sacral_point": [1.0, 2.0, 3.0]})
    rec.torso.save("torso.ply", ContentFile(b"ply"), save=False)
    rec.report_file.save("report.json", ContentFile(b"{}"), save=False)
    rec.save()
    return visit, rec


@pytest.fixture
def analysed(monkeypatch):
    """The landmarks each analysis was given (the engine is not run here)."""
    import clinic.analysis_step

    calls = []
    monkeypatch.setattr(clinic.analysis_step, "analyse_reconstruction", lambda rec: calls.append(rec.landmarks))
    return calls


@pytest.mark.django_db
@pytest.mark.parametrize("sacral", ["nan 0 0", "1 inf 2", "1e300 0 0", "0 0 -5001", "1 2", "1 2 3 4", "a b c"])
def test_a_bad_landmark_is_refused_and_the_other_is_not_stored_either(client, charlie, visit_with_torso,
                                                                       analysed, sacral):
    visit, rec = visit_with_torso
    client.force_login(charlie)
    r = client.post(f"/visits/{visit.pk}/landmarks", {"vertebra_prominens": "10 20 30", "sacral_point": sacral})
    assert r.status_code == 400 and b"sacral point" in r.content
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": [1.0, 2.0, 3.0]} and analysed == []


@pytest.mark.django_db
def test_a_good_correction_is_stored_and_analysed(client, charlie, visit_with_torso, analysed):
    visit, rec = visit_with_torso
    client.force_login(charlie)
    r = client.post(f"/visits/{visit.pk}/landmarks", {"vertebra_prominens": "10, 20, 30", "sacral_point": "-4 5 6"})
    assert r.status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks == {"vertebra_prominens": [10.0, 20.0, 30.0], "sacral_point": [-4.0, 5.0, 6.0]}
    assert analysed == [rec.landmarks]


@pytest.mark.django_db
def test_a_correction_whose_analysis_fails_is_undone_and_says_why(client, charlie, visit_with_torso, monkeypatch, caplog):
    import clinic.analysis_step

    def fails(rec):
        raise ValueError("the landmark lies off the torso")

    monkeypatch.setattr(clinic.analysis_step, "analyse_reconstruction", fails)
    visit, rec = visit_with_torso
    client.force_login(charlie)
    r = client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": "7 8 9"})
    assert r.status_code == 302  # the recomputation is a job (in the embedded default it ran in the request)
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": [1.0, 2.0, 3.0]} and not rec.landmark_history  # put back
    assert "the landmark lies off the torso" in caplog.text
    page = client.get(r["Location"]).content.decode()
    assert "The last landmark correction could not be applied" in page and "the correction was undone" in page and "the landmark lies off the torso" in page
