"""A patient's data exported whole (every row, every stored file) and erased whole (the trail of it survives)."""

import hashlib
import json
import zipfile

import pytest
from django.core.files.storage import default_storage
from django.core.management import CommandError, call_command

from clinic import records
from clinic.models import (ArmTask, AuditEvent, CaptureImage, CaptureSession, Comparison, Job, Patient,
                           Reconstruction, Visit)
from tests.patient_records import patient_with_records


@pytest.mark.django_db
def test_it_exports_every_row_and_every_referenced_file(clinic, tmp_path):
    patient, recs, comparison = patient_with_records(clinic)
    other, _, _ = patient_with_records(clinic, identifier="P-2", name="Someone Else")
    out = tmp_path / "p.zip"
    call_command("export_patient", str(patient.pk), "--out", str(out))

    with zipfile.ZipFile(out) as zf:
        data = json.loads(zf.read("records.json"))
        pks = {key: {row["pk"] for row in rows} for key, rows in data.items()}
        assert pks == {
            "patient": {patient.pk}, "visits": set(patient.visits.values_list("pk", flat=True)),
            "sessions": set(CaptureSession.objects.filter(visit__patient=patient).values_list("pk", flat=True)),
            "images": set(CaptureImage.objects.filter(session__visit__patient=patient).values_list("pk", flat=True)),
            "jobs": {r.job_id for r in recs},
            "arm_tasks": set(ArmTask.objects.filter(job__in=[r.job_id for r in recs]).values_list("pk", flat=True)),
            "reconstructions": {r.pk for r in recs}, "comparisons": {comparison.pk}}
        assert data["patient"][0]["fields"]["notes"] == "brace since May"
        assert data["sessions"][0]["fields"]["manifest"] == {"images": [{"camera": "A1", "file": "A1.png"}]}
        assert {r["fields"]["indices"]["lateral_deviation_mm"] for r in data["reconstructions"]} == {4.0, 5.0}

        expected = records.stored_names([*recs, comparison, *CaptureImage.objects.filter(session__visit__patient=patient),
                                         *ArmTask.objects.filter(job__in=[r.job_id for r in recs])])
        assert len(expected) == 2 * 6 + 2  # per visit: image, arm surface, torso, mesh, report, picture; map, deformation
        stored = {n[len("files/"):] for n in zf.namelist() if n.startswith("files/")}
        assert stored == expected
        for name in expected:
            with default_storage.open(name, "rb") as fh:
                assert zf.read(f"files/{name}") == fh.read()
        sums = json.loads(zf.read("files.json"))["files"]
        assert sums == {n: hashlib.sha256(zf.read(f"files/{n}")).hexdigest() for n in expected}
        assert not any(other.name in zf.read(n).decode(errors="replace") for n in zf.namelist())
    e = AuditEvent.objects.get(action=AuditEvent.EXPORT)
    assert (e.patient_id, e.detail["files"]) == (patient.pk, len(expected))


@pytest.mark.django_db
def test_it_erases_every_row_and_file_and_the_erase_event_survives(clinic, charlie, tmp_path):
    patient, recs, comparison = patient_with_records(clinic)
    other, other_recs, _ = patient_with_records(clinic, identifier="P-2", name="Someone Else")
    pk = patient.pk
    files = records.stored_names(row for qs in records.patient_records(patient).values() for row in qs)
    other_files = records.stored_names(row for qs in records.patient_records(other).values() for row in qs)
    AuditEvent.objects.create(action=AuditEvent.VIEW, user=charlie, username="charlie", patient_id=pk)

    with pytest.raises(CommandError, match="--yes"):
        call_command("erase_patient", str(pk))
    assert Patient.objects.filter(pk=pk).exists()

    call_command("erase_patient", str(pk), "--yes")
    assert not Patient.objects.filter(pk=pk).exists()
    assert not Visit.objects.filter(patient_id=pk).exists()
    assert not CaptureSession.objects.filter(pk__in=[r.session_id for r in recs]).exists()
    assert not Job.objects.filter(pk__in=[r.job_id for r in recs]).exists()
    assert not Reconstruction.objects.filter(pk__in=[r.pk for r in recs]).exists()
    assert not Comparison.objects.filter(pk=comparison.pk).exists()
    assert files and not any(default_storage.exists(n) for n in files)
    assert all(default_storage.exists(n) for n in other_files)  # the other patient is untouched
    assert Reconstruction.objects.filter(pk__in=[r.pk for r in other_recs]).count() == 2

    erase = AuditEvent.objects.get(action=AuditEvent.ERASE)
    assert (erase.patient_id, erase.object_type) == (pk, "patient")
    assert erase.detail["rows"] == {"patient": 1, "visits": 2, "sessions": 2, "images": 2, "jobs": 2, "arm_tasks": 2,
                                    "reconstructions": 2, "comparisons": 1, "files": len(files)}
    assert AuditEvent.objects.filter(patient_id=pk, action=AuditEvent.VIEW).count() == 1  # the trail survives
    assert not AuditEvent.objects.filter(patient_id=pk, action=AuditEvent.DELETE).exists()  # one event, not a row each


@pytest.mark.django_db
def test_it_refuses_to_erase_a_patient_whose_job_runs(clinic):
    patient, recs, _ = patient_with_records(clinic)
    Job.objects.filter(pk=recs[1].job_id).update(state=Job.RUNNING)
    with pytest.raises(CommandError, match=r"job\(s\) not finished .* running"):
        call_command("erase_patient", str(patient.pk), "--yes")
    assert Reconstruction.objects.filter(session__visit__patient=patient).count() == 2
    assert not AuditEvent.objects.filter(action=AuditEvent.ERASE).exists()
