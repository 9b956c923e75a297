"""Restore a backup made by ``backup`` into an empty installation: database and stored files.

The backup is checked whole first (the dump's and every file's sha256), so a
damaged backup is refused before anything is written. Then the database is
migrated, the rows loaded, the files stored under their names, and every
file read back from the storage and checked against its sha256.
"""

import json
from pathlib import Path

from django.core.files import File
from django.core.files.storage import default_storage
from django.core.management import call_command
from django.core.management.base import BaseCommand, CommandError

from clinic import records
from clinic.management.commands.backup import FORMAT, local_path, row_counts, sha256_file
from clinic.models import Patient


class Command(BaseCommand):
    help = "Restore a backup folder (from manage.py backup) into this installation's database and storage."

    def add_arguments(self, parser):
        parser.add_argument("directory", help="the backup folder")
        parser.add_argument("--force", action="store_true",
                            help="load even though the database already has patients (rows with the same ids are "
                                 "overwritten)")

    def handle(self, *args, directory, force=False, **options):
        root = Path(directory)
        try:
            manifest = json.loads((root / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise CommandError(f"{root} is not a backup: {exc}") from None
        if manifest.get("format") != FORMAT:
            raise CommandError(f"{root}: unknown backup format {manifest.get('format')!r}")
        dump = root / manifest["database"]["file"]
        damaged = [] if sha256_file(dump) == manifest["database"]["sha256"] else [dump.name]
        for name, meta in manifest["files"].items():
            path = local_path(root / "files", name)
            if not path.is_file() or sha256_file(path) != meta["sha256"]:
                damaged.append(name)
        if damaged:
            raise CommandError(f"the backup is damaged (wrong or missing: {', '.join(damaged[:10])}"
                               f"{' ...' if len(damaged) > 10 else ''}); nothing was restored")

        call_command("migrate", interactive=False, verbosity=0)
        if Patient.objects.exists() and not force:
            raise CommandError(f"this installation already has {Patient.objects.count()} patient(s): restore into an "
                               "empty one (or --force to load over them)")
        call_command("loaddata", str(dump), verbosity=0)  # one transaction

        for name, meta in manifest["files"].items():
            if default_storage.exists(name):
                if records.sha256_of_stored(name) == meta["sha256"]:
                    continue
                default_storage.delete(name)  # a stale file under that name: the backup's is the one rows mean
            with open(local_path(root / "files", name), "rb") as fh:
                stored = default_storage.save(name, File(fh))
            if stored != name:
                raise CommandError(f"the storage saved {name} as {stored}: the rows would not find it")

        wrong = [name for name, meta in manifest["files"].items() if records.sha256_of_stored(name) != meta["sha256"]]
        if wrong:
            raise CommandError(f"{len(wrong)} file(s) differ from the backup once stored: {', '.join(wrong[:10])}")
        counts = row_counts()
        short = {label: (n, counts.get(label, 0)) for label, n in manifest["counts"].items() if counts.get(label, 0) < n}
        if short:
            raise CommandError("rows missing after loading: " + ", ".join(
                f"{label} {have} of {n}" for label, (n, have) in short.items()))
        self.stdout.write(f"restored {sum(manifest['counts'].values())} rows and {len(manifest['files'])} files "
                          f"(every sha256 checked) from {root}")
