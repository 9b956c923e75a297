"""Stored files against the rows that name them: files no row references (orphans) and rows whose file is gone.

An orphan is what an upload or a job left when it failed between storing a
file and committing the row that names it (e.g. the database lost at that
moment: the file is kept, since the row may have been committed). A file
younger than ``grace`` is never an orphan: uploads and jobs store their files
before their rows name them. Run by ``manage.py check_files`` and by beat
(``clinic.tasks.check_files``).
"""

import datetime as dt
import logging
import posixpath
from dataclasses import dataclass, field

from django.apps import apps
from django.core.files.storage import default_storage
from django.utils import timezone

from . import records

log = logging.getLogger(__name__)
GRACE = dt.timedelta(hours=1)


@dataclass
class Report:
    stored: int = 0
    referenced: int = 0
    orphans: list = field(default_factory=list)  # storage names no row references, older than the grace
    young: int = 0  # unreferenced but younger than the grace: maybe an upload in flight
    missing: list = field(default_factory=list)  # (model label, pk, storage name) whose file is not stored
    removed: list = field(default_factory=list)

    @property
    def clean(self) -> bool:
        return not self.missing and len(self.removed) == len(self.orphans)

    def summary(self) -> str:
        return (f"{self.stored} stored files, {self.referenced} named by rows: {len(self.orphans)} orphaned "
                f"({len(self.removed)} removed), {self.young} unreferenced but younger than the grace, "
                f"{len(self.missing)} rows' files missing")


def stored_names(storage=default_storage, folder=""):
    """Every file of the storage (recursively)."""
    try:
        dirs, files = storage.listdir(folder)
    except FileNotFoundError:  # nothing stored yet
        return
    for name in files:
        yield posixpath.join(folder, name) if folder else name
    for d in dirs:
        yield from stored_names(storage, posixpath.join(folder, d) if folder else d)


def referencing_rows():
    """(model label, pk, storage name) for every file a row of the clinic's records names."""
    for model in apps.get_app_config("clinic").get_models():
        if records.refers_to_files(model):
            for row in model.objects.all().iterator():
                for name in records.stored_names([row]):
                    yield model._meta.label, row.pk, name


def check(remove_orphans=False, grace=GRACE, storage=default_storage) -> Report:
    stored = set(stored_names(storage))
    rows = list(referencing_rows())
    referenced = {name for _, _, name in rows}
    report = Report(stored=len(stored), referenced=len(referenced))
    report.missing = sorted((label, pk, name) for label, pk, name in rows if name not in stored)
    cutoff = timezone.now() - grace
    for name in sorted(stored - referenced):
        if storage.get_modified_time(name) > cutoff:
            report.young += 1
        else:
            report.orphans.append(name)
    if remove_orphans and report.orphans:
        still = records.all_stored_names()  # named since the listing (a late commit): kept
        for name in report.orphans:
            if name not in still:
                storage.delete(name)
                report.removed.append(name)
    for name in report.orphans:
        log.warning("stored file %s: no row references it%s", name, " (removed)" if name in report.removed else "")
    for label, pk, name in report.missing:
        log.error("%s %s names the stored file %s, which is missing", label, pk, name)
    return report
