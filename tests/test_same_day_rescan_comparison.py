"""Any two scans can be compared, a same-day re-scan too: it opens, labelled as the scanner's repeatability."""

import pytest
from django.core.files.base import ContentFile

from tests.test_browser_comparison import torso_ply, patient_with_two_visits  # noqa: F401 (fixture)


def _rescan(visit, rotation, seed):
    from clinic.analysis_step import analyse_reconstruction
    from clinic.models import CaptureSession, Job, Reconstruction

    first = visit.sessions.first()
    session = CaptureSession.objects.create(rig=first.rig, kind="torso", visit=visit, manifest={"images": []},
                                            manifest_sha256="re", idempotency_key=f"re-{seed}",
                                            captured_at=str(visit.date), state=CaptureSession.FINALIZED)
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=first.rig, session=session, state=Job.SUCCEEDED,
                             percent=100, stage="done")
    rec = Reconstruction(job=job, session=session, status="ok", points=1, report={"registration": {"pairs": []}})
    rec.torso.save("torso.ply", ContentFile(torso_ply(rotation, seed)), save=False)
    rec.report_file.save("report.json", ContentFile(b"{}"), save=False)
    rec.save()
    return analyse_reconstruction(rec)


@pytest.mark.django_db
def test_a_same_day_rescan_opens_labelled_as_repeatability(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    p = patient_with_two_visits
    first = p.visits.first()
    original = Reconstruction.objects.get(session__visit=first)
    again = _rescan(first, 5.0, 7)
    client.force_login(charlie)
    # the history offers every scan, the re-scan among them
    history = client.get(f"/patients/{p.pk}/").content.decode()
    assert "scan 1 of 2" in history and "scan 2 of 2" in history
    r = client.post(f"/patients/{p.pk}/compare/?earlier_scan={original.pk}&later_scan={again.pk}", follow=True)
    assert r.status_code == 200
    html = r.content.decode()
    assert "Same-day re-scan" in html and "repeatability" in html and "not a change" in html
    assert 'id="deformation"' in html
    # choosing the same visit twice compares its two scans (it was a 404)
    r = client.post(f"/patients/{p.pk}/compare/?earlier={first.pk}&later={first.pk}", follow=True)
    assert r.status_code == 200 and "Same-day re-scan" in r.content.decode()


@pytest.mark.django_db
def test_a_scan_against_itself_is_refused_in_words(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Reconstruction

    p = patient_with_two_visits
    rec = Reconstruction.objects.get(session__visit=p.visits.first())
    client.force_login(charlie)
    r = client.get(f"/patients/{p.pk}/compare/?earlier_scan={rec.pk}&later_scan={rec.pk}")
    assert r.status_code == 400 and "Choose two different scans" in r.content.decode()
