"""A patient with two visits, their scans, results and a comparison: rows and stored files, no engine run."""

from django.core.files.base import ContentFile
from django.core.files.storage import default_storage

from clinic.models import (ArmTask, CaptureImage, CaptureSession, Comparison, Job, Patient, Reconstruction, Rig,
                           Visit)


def patient_with_records(clinic, rig=None, identifier="P-1", name="Robin Audit"):
    """``(patient, [reconstruction, reconstruction], comparison)``; every file field and picture is stored."""
    rig = rig or Rig.objects.get_or_create(clinic=clinic, serial="RIG-R", defaults={"description": {}})[0]
    patient = Patient.objects.create(clinic=clinic, identifier=identifier, name=name, notes="brace since May")
    recs = []
    for k, date in enumerate(["2026-07-01", "2026-11-01"]):
        visit = Visit.objects.create(patient=patient, date=date, reason=f"visit {k}", notes=f"Risser {k + 1}")
        session = CaptureSession.objects.create(
            rig=rig, kind="torso", visit=visit, manifest={"images": [{"camera": "A1", "file": "A1.png"}]},
            manifest_sha256="0" * 64, idempotency_key=f"{identifier}-{k}", captured_at=date,
            state=CaptureSession.FINALIZED)
        image = CaptureImage.objects.create(session=session, camera="A1", file_name="A1.png", sha256="0" * 64)
        image.file.save("A1.png", ContentFile(b"image %d of %s" % (k, identifier.encode())))
        job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED)
        arm = ArmTask.objects.create(job=job, arm="A", state=Job.SUCCEEDED)
        arm.surface.save("arm-A.npz", ContentFile(b"arm surface %d" % k))
        rec = Reconstruction(job=job, session=session, report={"status": "ok"}, status="ok", points=3,
                             indices={"lateral_deviation_mm": 4.0 + k})
        rec.torso.save("torso.ply", ContentFile(b"ply torso %d" % k), save=False)
        rec.mesh.save("torso-mesh.ply", ContentFile(b"ply mesh %d" % k), save=False)
        rec.report_file.save("report.json", ContentFile(b'{"status": "ok"}'), save=False)
        rec.pictures = {"back": default_storage.save(f"pictures/{identifier}-{k}-back.png", ContentFile(b"png"))}
        rec.save()
        recs.append(rec)
    comparison = Comparison(earlier=recs[0], later=recs[1], report={"rms_mm": 1.5})
    comparison.deformation.save("deformation.ply", ContentFile(b"ply deformation"), save=False)
    comparison.pictures = {"map": default_storage.save(f"pictures/{identifier}-map.png", ContentFile(b"png map"))}
    comparison.save()
    return patient, recs, comparison


def two_torsos(clinic, serial, identifier, name, indices=None, mesh=None):
    """``(patient, [earlier, later])``: two visits, each with a good torso (no images, arms or pictures).

    ``mesh`` (bytes with a ``%d`` for the visit's index) stores each torso's display mesh too.
    """
    rig = Rig.objects.create(clinic=clinic, serial=serial, description={})
    patient = Patient.objects.create(clinic=clinic, identifier=identifier, name=name)
    recs = []
    for k, date in enumerate(["2026-07-01", "2026-11-01"]):
        visit = Visit.objects.create(patient=patient, date=date)
        session = CaptureSession.objects.create(rig=rig, kind="torso", visit=visit, manifest={"images": []},
                                                manifest_sha256=str(k), idempotency_key=str(k), captured_at=date,
                                                state=CaptureSession.FINALIZED)
        job = Job.objects.create(kind=Job.RECONSTRUCTION, rig=rig, session=session, state=Job.SUCCEEDED)
        rec = Reconstruction(job=job, session=session, status="ok", points=1, report={}, indices=indices or {})
        rec.torso.save("torso.ply", ContentFile(b"ply torso %d" % k), save=False)
        if mesh is not None:
            rec.mesh.save("torso-mesh.ply", ContentFile(mesh % k), save=False)
        rec.report_file.save("report.json", ContentFile(b"{}"), save=False)
        rec.save()
        recs.append(rec)
    return patient, recs


def correct_sacral_point(client, user, visit):
    """``user`` moves the visit's sacral point 5 mm left and 20 mm up on the visit page's form.

    Returns ``(reconstruction, automatic position, corrected position, response)`` (mm, the torso's frame).
    """
    rec = Reconstruction.objects.get(session__visit=visit)
    auto = rec.indices["landmarks"]["sacral_point"]["position_mm"]
    moved = [auto[0] + 5.0, auto[1], auto[2] + 20.0]
    client.force_login(user)
    response = client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": " ".join(map(str, moved))})
    return rec, auto, moved, response
