"""Read the audit trail: who viewed, downloaded, created, changed or deleted which patient's data, and when."""

import datetime
import json

from django.core.management.base import BaseCommand, CommandError
from django.utils import timezone
from django.utils.dateparse import parse_date, parse_datetime

from clinic.models import AuditEvent


def is_date(value):
    return len(value) == 10  # YYYY-MM-DD (parse_datetime would take it too, as midnight)


def moment(value, end_of_day=False):
    """A date (the whole day: its start, or with ``end_of_day`` the next day's start) or an ISO date-time."""
    try:
        day = parse_date(value) if is_date(value) else None
        when = None if day else parse_datetime(value)
    except ValueError:
        day = when = None
    if day is not None:
        when = datetime.datetime.combine(day + datetime.timedelta(days=1 if end_of_day else 0), datetime.time())
    elif when is None:
        raise CommandError(f"{value!r} is not a date (YYYY-MM-DD) or a date-time (YYYY-MM-DDTHH:MM)")
    return timezone.make_aware(when) if timezone.is_naive(when) else when


class Command(BaseCommand):
    help = "List audit events, oldest first, by patient, user and date."

    def add_arguments(self, parser):
        parser.add_argument("--patient", type=int, help="a patient's id (erased patients included)")
        parser.add_argument("--user", help="a user name (or a rig's serial)")
        parser.add_argument("--since", help="from this date (YYYY-MM-DD) or date-time")
        parser.add_argument("--until", help="up to this date (the whole day) or date-time")
        parser.add_argument("--json", action="store_true", help="a JSON array instead of lines")

    def handle(self, *args, patient=None, user=None, since=None, until=None, **options):
        events = AuditEvent.objects.order_by("time", "id")
        if patient is not None:
            events = events.filter(patient_id=patient)
        if user:
            events = events.filter(username=user) | events.filter(rig_serial=user)
        if since:
            events = events.filter(time__gte=moment(since))
        if until:
            events = events.filter(time__lt=moment(until, end_of_day=True)) if is_date(until) \
                else events.filter(time__lte=moment(until))
        rows = [{"time": e.time.isoformat(), "user": e.username, "rig": e.rig_serial, "clinic": e.clinic_id,
                 "patient": e.patient_id, "action": e.action, "object_type": e.object_type,
                 "object_id": e.object_id, "method": e.method, "path": e.path, "status": e.status,
                 "remote_addr": e.remote_addr, "detail": e.detail} for e in events.iterator()]
        if options["json"]:
            self.stdout.write(json.dumps(rows, indent=1))
            return
        for r in rows:
            who = r["user"] or (f"rig {r['rig']}" if r["rig"] else "-")
            what = f"{r['object_type']} {r['object_id']}".strip() or "-"
            where = f"{r['method']} {r['path']} {r['status'] or ''}".strip() or "-"
            self.stdout.write(f"{r['time']}  {who:<16} {r['action']:<12} patient {r['patient'] or '-':<6} "
                              f"{what:<24} {where} {r['remote_addr'] or ''}".rstrip())
        self.stdout.write(f"{len(rows)} event(s)")
