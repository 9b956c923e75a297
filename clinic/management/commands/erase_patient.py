"""Erase one patient: every row and every stored file, for good (export it first if it must be handed over).

The audit trail keeps that it happened (an "erase" event with the counts);
it names the patient by id only.
"""

import getpass

from django.core.management.base import BaseCommand, CommandError

from clinic import records
from clinic.models import Patient


class Command(BaseCommand):
    help = "Delete every row and stored file of one patient (refused while one of their jobs runs)."

    def add_arguments(self, parser):
        parser.add_argument("patient", type=int, help="the patient's id (as in /patients/ID/)")
        parser.add_argument("--yes", action="store_true", help="really erase: there is no undo")

    def handle(self, *args, patient, yes=False, **options):
        p = Patient.objects.filter(pk=patient).first()
        if p is None:
            raise CommandError(f"no patient {patient}")
        if not yes:
            raise CommandError(f"this erases {p} and all their scans for good; run again with --yes")
        try:
            counts, kept = records.erase(p, username=f"os:{getpass.getuser()}")
        except records.ErasureRefused as exc:
            raise CommandError(str(exc)) from None
        for name in kept:
            self.stderr.write(f"could not delete the stored file {name}: delete it by hand")
        self.stdout.write(f"erased patient {patient}: " + ", ".join(f"{n} {key}" for key, n in counts.items()))
