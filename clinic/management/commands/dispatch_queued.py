"""Send again the jobs the broker never got (or lost) and the steps whose worker died.

What beat's ``redispatch-stalled-jobs`` does every ``JOB_SWEEP_SECONDS``; run
it by hand after a broker outage, or from cron where beat is not running.
"""

from django.core.management.base import BaseCommand

from clinic import pipeline


class Command(BaseCommand):
    help = ("Re-dispatch jobs queued (not claimed) for longer than JOB_REDISPATCH_SECONDS, and steps whose "
            "claim's lease lapsed.")

    def add_arguments(self, parser):
        parser.add_argument("--older-than", type=int, default=None, metavar="SECONDS",
                            help="re-dispatch what waited longer than this (default: JOB_REDISPATCH_SECONDS)")

    def handle(self, *args, older_than=None, **options):
        sent = pipeline.redispatch_stalled(older_than=older_than)
        for name, *ids in sent:
            self.stdout.write(f"sent {name} {' '.join(map(str, ids))}")
        self.stdout.write(f"{len(sent)} step(s) re-dispatched")
