"""A backup of a PostgreSQL installation, restored into another empty PostgreSQL database and media folder, has
every row and file; sequences continue after the restored ids (a new row after the restore does not collide)."""

import hashlib
import json
import os

from tests.pg_server import run_manage, run_sql, template_database
from tests.services import require_postgres

RECORDS = ("from clinic.models import Clinic; from tests.patient_records import patient_with_records;"
           "c = Clinic.objects.get(); patient_with_records(c, identifier='P-10'); patient_with_records(c, identifier='P-11')")
COUNTS = ("import json; from clinic.management.commands.backup import row_counts; print(json.dumps(row_counts()))")


def installation(tmp_path, name, dbname):
    return {**os.environ, "DEBUG": "true", "DJANGO_SETTINGS_MODULE": "clinic.settings", "CELERY_BROKER_URL": "",
            "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{dbname}", "TORSOSCAN_VAR": str(tmp_path / name),
            "MEDIA_ROOT": str(tmp_path / name / "media"),
            "STORAGE_BACKEND": "django.core.files.storage.FileSystemStorage"}


def test_it_restores_a_postgresql_backup_into_an_empty_postgresql_installation(tmp_path):
    require_postgres("postgres")
    source, target = f"torsoscan_backup_src_{os.getpid()}", f"torsoscan_backup_dst_{os.getpid()}"
    for db in (source, target):
        run_sql(f'DROP DATABASE IF EXISTS "{db}" WITH (FORCE)')
    src = installation(tmp_path, "source", source)
    dst = installation(tmp_path, "target", target)
    run_sql(f'CREATE DATABASE "{source}" TEMPLATE "{template_database(src)}"')
    run_sql(f'CREATE DATABASE "{target}"')  # empty: restore migrates it
    try:
        run_manage(src, "shell", "-c", RECORDS)
        backup = tmp_path / "backup"
        run_manage(src, "backup", "--out", str(backup))
        manifest = json.loads((backup / "manifest.json").read_text())
        assert manifest["database"]["vendor"] == "postgresql" and len(manifest["files"]) == 2 * 14

        run_manage(dst, "restore", str(backup))
        media = tmp_path / "target" / "media"
        assert {p.relative_to(media).as_posix() for p in media.rglob("*") if p.is_file()} == set(manifest["files"])
        for name, meta in manifest["files"].items():
            assert hashlib.sha256((media / name).read_bytes()).hexdigest() == meta["sha256"], name
        counts = json.loads(run_manage(dst, "shell", "-c", COUNTS).strip().splitlines()[-1])
        assert {k: v for k, v in counts.items() if v} == {k: v for k, v in manifest["counts"].items() if v}
        rows = "SELECT p.identifier, v.date, r.torso FROM clinic_reconstruction r JOIN clinic_capturesession s " \
               "ON s.id = r.session_id JOIN clinic_visit v ON v.id = s.visit_id JOIN clinic_patient p " \
               "ON p.id = v.patient_id ORDER BY r.id"
        assert run_sql(rows, target) == run_sql(rows, source) and len(run_sql(rows, target)) == 4
        # the ids continue: a patient created after the restore gets a new id, not a restored one's
        run_manage(dst, "shell", "-c", "from clinic.models import Clinic, Patient;"
                                       "Patient.objects.create(clinic=Clinic.objects.get(), identifier='P-new')")
        assert run_sql("SELECT count(*) FROM clinic_patient", target) == [(counts["clinic.Patient"] + 1,)]
    finally:
        for db in (source, target):
            run_sql(f'DROP DATABASE IF EXISTS "{db}" WITH (FORCE)')
