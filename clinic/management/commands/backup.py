"""A consistent backup of the database and the stored files together.

The rows are dumped (``dumpdata`` of the clinic, auth and django_celery_beat)
in one read transaction (REPEATABLE READ on PostgreSQL: one snapshot for every
table), and every stored file a row of that snapshot refers to is copied in the
same transaction; files are stored before a row names them and deleted only
after no row does, so the copy finds them all. ``manifest.json`` lists each
file's sha256, the dump's, and each model's row count; ``restore`` checks them.
"""

import datetime
import hashlib
import json
from pathlib import Path, PurePosixPath

from django.apps import apps
from django.core.files.storage import default_storage
from django.core.management import call_command
from django.core.management.base import BaseCommand, CommandError
from django.db import connection, transaction

from clinic import records

APPS = ["clinic", "auth", "django_celery_beat"]
# permissions and content types are made by migrate on the target; users and groups refer to them by natural key
EXCLUDE = ["auth.permission"]
FORMAT = "torsoscan-backup/1"


def local_path(root: Path, name: str) -> Path:
    """Where the storage name ``name`` goes under ``root`` (never outside it)."""
    parts = PurePosixPath(name).parts
    if not parts or PurePosixPath(name).is_absolute() or ".." in parts:
        raise CommandError(f"refusing the storage name {name!r}")
    return root.joinpath(*parts)


def row_counts():
    return {model._meta.label: model.objects.count()
            for label in APPS for model in apps.get_app_config(label).get_models()
            if model._meta.label.lower() not in EXCLUDE}


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(records.CHUNK), b""):
            digest.update(chunk)
    return digest.hexdigest()


class Command(BaseCommand):
    help = "Back up the database (as JSON) and every stored file a row refers to, consistently, into a new folder."

    def add_arguments(self, parser):
        parser.add_argument("--out", required=True, help="a folder that does not exist yet, or is empty")

    def handle(self, *args, out, **options):
        out = Path(out)
        if out.exists() and any(out.iterdir()):
            raise CommandError(f"{out} is not empty: back up into a new folder")
        (out / "files").mkdir(parents=True, exist_ok=True)
        files, missing = {}, []
        with transaction.atomic():
            if connection.vendor == "postgresql" and connection.get_autocommit() is False \
                    and len(connection.atomic_blocks) == 1:
                # the first statement of the transaction: every table is read from one snapshot
                with connection.cursor() as cursor:
                    cursor.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")
            with open(out / "database.json", "w", encoding="utf-8") as fh:
                call_command("dumpdata", *APPS, exclude=EXCLUDE, natural_foreign=True, natural_primary=True,
                             stdout=fh, verbosity=0)
            counts = row_counts()
            for name in sorted(records.all_stored_names()):
                target = local_path(out / "files", name)
                target.parent.mkdir(parents=True, exist_ok=True)
                digest, size = hashlib.sha256(), 0
                try:
                    with default_storage.open(name, "rb") as src, open(target, "wb") as dst:
                        for chunk in iter(lambda: src.read(records.CHUNK), b""):
                            digest.update(chunk)
                            size += len(chunk)
                            dst.write(chunk)
                except FileNotFoundError:
                    target.unlink(missing_ok=True)
                    missing.append(name)
                    continue
                files[name] = {"sha256": digest.hexdigest(), "size": size}
        manifest = {"format": FORMAT, "created": datetime.datetime.now(datetime.timezone.utc).isoformat(),
                    "database": {"file": "database.json", "sha256": sha256_file(out / "database.json"),
                                 "vendor": connection.vendor},
                    "counts": counts, "files": files, "missing": missing}
        (out / "manifest.json").write_text(json.dumps(manifest, indent=1), encoding="utf-8")
        for name in missing:
            self.stderr.write(f"a row refers to {name}, which is not in the storage")
        self.stdout.write(f"{out}: {sum(counts.values())} rows, {len(files)} files"
                          + (f", {len(missing)} missing" if missing else ""))
        if missing:
            raise CommandError(f"{len(missing)} file(s) referred to are missing from the storage (listed above); "
                               "the backup holds everything else")
