"""Each torso is compared with every earlier visit's and with the earlier captures of its own visit."""

import pytest
from django.core.files.base import ContentFile

from tests.test_browser_comparison import torso_ply


def _reconstruction(rig, visit, rotation, seed):
    from clinic.models import CaptureSession, Job, Reconstruction

    session = CaptureSession.objects.create(rig=rig, kind="torso", visit=visit, manifest={"images": []},
                                            manifest_sha256=str(seed), idempotency_key=str(seed),
                                            captured_at=str(visit.date), state=CaptureSession.FINALIZED)
    job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED)
    rec = Reconstruction(job=job, session=session, status="ok", points=1, report={})
    rec.torso.save("torso.ply", ContentFile(torso_ply(rotation, seed)), save=False)
    rec.report_file.save("report.json", ContentFile(b"{}"), save=False)
    rec.save()
    return rec


@pytest.mark.django_db
def test_repeat_pairs_give_the_mdc_and_later_visits_are_compared_with_it(clinic):
    from clinic.analysis_step import analyse_reconstruction, clinic_mdc
    from clinic.models import Comparison, Patient, Rig, Visit
    from clinic.pipeline import compare_with_earlier

    rig = Rig.objects.create(clinic=clinic, serial="RIG-C", description={})
    patient = Patient.objects.create(clinic=clinic, identifier="P-9", name="Sam")
    baseline = Visit.objects.create(patient=patient, date="2026-07-01")
    later = Visit.objects.create(patient=patient, date="2026-11-01")
    a = _reconstruction(rig, baseline, 5.0, 1)
    b = _reconstruction(rig, baseline, 5.0, 2)
    c = _reconstruction(rig, later, 10.0, 3)
    for rec in (a, b, c):
        analyse_reconstruction(rec)
        compare_with_earlier(rec)
    pairs = {(x.earlier_id, x.later_id): x for x in Comparison.objects.all()}
    assert set(pairs) == {(a.pk, b.pk), (b.pk, c.pk)}  # the later visit against the latest baseline torso
    assert pairs[(a.pk, b.pk)].is_repeat and not pairs[(b.pk, c.pk)].is_repeat
    mdc = clinic_mdc(clinic, usable_only=False)
    assert mdc["average_normal_distance_mm"]["n"] == 1 and "surface_rotation_deg.max" in mdc
    # one repeat pair flags nothing: its MDC's 95 % interval spans a factor of 70
    lo, hi = mdc["surface_rotation_deg.max"]["ci95"]
    assert hi / lo > 50
    # the clinic's own figures are not used: only the scanner's repeatability, labelled so, flags
    assert all(v["source"] == "scanner" for v in clinic_mdc(clinic).values())
    change = pairs[(b.pk, c.pk)].report
    assert change["average_normal_distance_mm"] > pairs[(a.pk, b.pk)].report["average_normal_distance_mm"]
    assert set(pairs[(b.pk, c.pk)].pictures) == {"deformation"}
