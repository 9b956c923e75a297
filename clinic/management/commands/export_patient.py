"""One patient's data, whole, in one zip: what a patient (or their parents) may ask to receive.

``records.json`` holds every row (the patient, visits with their notes,
capture sessions with their manifests and images, jobs, reconstructions with
their reports and indices, comparisons) in Django's serialization;
``files/`` every stored file they refer to (images, torso PLYs, reports,
pictures), under its storage name; ``files.json`` each file's sha256.
"""

import getpass
import hashlib
import json
import zipfile
from pathlib import Path

from django.core.files.storage import default_storage
from django.core.management.base import BaseCommand, CommandError

from clinic import audit, records
from clinic.models import AuditEvent, Patient


class Command(BaseCommand):
    help = "Export one patient's records and stored files to a zip."

    def add_arguments(self, parser):
        parser.add_argument("patient", type=int, help="the patient's id (as in /patients/ID/)")
        parser.add_argument("--out", required=True, help="the zip to write (not overwritten)")

    def handle(self, *args, patient, out, **options):
        p = Patient.objects.filter(pk=patient).first()
        if p is None:
            raise CommandError(f"no patient {patient}")
        out = Path(out)
        if out.exists():
            raise CommandError(f"{out} exists: name a new file")
        rows = records.patient_records(p)
        names = records.stored_names(row for qs in rows.values() for row in qs)
        sums, missing = {}, []
        with zipfile.ZipFile(out, "x", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("records.json", records.as_json(rows))
            for name in sorted(names):
                if not default_storage.exists(name):
                    missing.append(name)
                    continue
                digest = hashlib.sha256()
                with default_storage.open(name, "rb") as src, zf.open(f"files/{name}", "w") as dst:
                    for chunk in iter(lambda: src.read(records.CHUNK), b""):
                        digest.update(chunk)
                        dst.write(chunk)
                sums[name] = digest.hexdigest()
            zf.writestr("files.json", json.dumps({"files": sums, "missing": missing}, indent=1))
        audit.record(AuditEvent.EXPORT, username=f"os:{getpass.getuser()}", patient_id=p.pk, clinic_id=p.clinic_id,
                     object_type="patient", object_id=p.pk,
                     detail={"rows": {key: qs.count() for key, qs in rows.items()}, "files": len(sums),
                             "out": str(out)})
        for name in missing:
            self.stderr.write(f"missing from storage: {name}")
        self.stdout.write(f"{out}: {sum(qs.count() for qs in rows.values())} rows, {len(sums)} files")
