"""A backup restored into a fresh installation (another SQLite database and media folder) has every row and file."""

import hashlib
import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from django.core.management import call_command

from clinic.models import AuditEvent, CaptureImage, Comparison, Patient, Reconstruction, Visit
from tests.patient_records import patient_with_records

ROOT = Path(__file__).resolve().parents[1]


def _restore(backup, tmp_path, *args):
    env = {**os.environ, "DEBUG": "true", "DATABASE_URL": f"sqlite:///{tmp_path / 'restored.sqlite3'}",
           "MEDIA_ROOT": str(tmp_path / "restored-media"), "TORSOSCAN_VAR": str(tmp_path / "var"),
           "STORAGE_BACKEND": "django.core.files.storage.FileSystemStorage"}
    return subprocess.run([sys.executable, "manage.py", "restore", str(backup), *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.django_db
def test_it_restores_a_backup_into_a_fresh_installation_with_every_file_and_row(clinic, charlie, tmp_path):
    patient, recs, comparison = patient_with_records(clinic)
    patient_with_records(clinic, identifier="P-2", name="Someone Else")
    AuditEvent.objects.create(action=AuditEvent.VIEW, user=charlie, username="charlie", patient_id=patient.pk)
    backup = tmp_path / "backup"
    call_command("backup", "--out", str(backup))

    manifest = json.loads((backup / "manifest.json").read_text())
    assert len(manifest["files"]) == 2 * 14 and not manifest["missing"]

    r = _restore(backup, tmp_path)
    assert r.returncode == 0, r.stderr
    media = tmp_path / "restored-media"
    for name, meta in manifest["files"].items():
        assert hashlib.sha256((media / name).read_bytes()).hexdigest() == meta["sha256"], name
    assert {str(p.relative_to(media)) for p in media.rglob("*") if p.is_file()} == set(manifest["files"])

    db = sqlite3.connect(tmp_path / "restored.sqlite3")
    count = lambda table: db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]  # noqa: E731
    for model in (Patient, Visit, CaptureImage, Reconstruction, Comparison, AuditEvent):
        assert count(model._meta.db_table) == model.objects.count() == manifest["counts"][model._meta.label]
    assert db.execute("SELECT username FROM auth_user WHERE username = 'charlie'").fetchone() == ("charlie",)
    assert db.execute("SELECT torso FROM clinic_reconstruction WHERE id = ?", (recs[0].pk,)).fetchone() == (
        recs[0].torso.name,)

    again = _restore(backup, tmp_path)  # the installation is no longer empty
    assert again.returncode != 0 and "already has 2 patient(s)" in again.stderr


@pytest.mark.django_db
def test_it_refuses_a_damaged_backup_before_restoring_anything(clinic, tmp_path):
    patient_with_records(clinic)
    backup = tmp_path / "backup"
    call_command("backup", "--out", str(backup))
    victim = next(p for p in (backup / "files").rglob("*.ply"))
    victim.write_bytes(b"bit rot")
    r = _restore(backup, tmp_path)
    assert r.returncode != 0 and "damaged" in r.stderr and victim.name in r.stderr
    assert not (tmp_path / "restored.sqlite3").exists() and not (tmp_path / "restored-media").exists()
