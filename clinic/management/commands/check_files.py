"""Report stored files no row references and rows whose file is missing; ``--remove-orphans`` deletes the former.

What beat's ``check-stored-files`` runs (reporting only). Exits 1 while
anything is wrong, so cron or a monitor can alert.
"""

import datetime as dt

from django.core.management.base import BaseCommand, CommandError

from clinic import filecheck


class Command(BaseCommand):
    help = "Report stored files that no row references and rows whose stored file is missing."

    def add_arguments(self, parser):
        parser.add_argument("--remove-orphans", action="store_true",
                            help="delete the stored files no row references (older than the grace)")
        parser.add_argument("--grace-minutes", type=int, default=int(filecheck.GRACE.total_seconds() // 60),
                            help="younger unreferenced files may belong to an upload in flight: left alone "
                                 "(default %(default)s)")

    def handle(self, *args, remove_orphans=False, grace_minutes=60, **options):
        if grace_minutes < 0:
            raise CommandError(f"--grace-minutes {grace_minutes}: must be 0 or more")
        report = filecheck.check(remove_orphans=remove_orphans, grace=dt.timedelta(minutes=grace_minutes))
        for name in report.orphans:
            self.stdout.write(f"orphan {name}{' (removed)' if name in report.removed else ''}")
        for label, pk, name in report.missing:
            self.stdout.write(f"missing {name} (named by {label} {pk})")
        self.stdout.write(report.summary())
        if not report.clean:
            raise CommandError("stored files and rows disagree (above)"
                               + ("" if remove_orphans or not report.orphans else
                                  "; --remove-orphans deletes the orphans"))
