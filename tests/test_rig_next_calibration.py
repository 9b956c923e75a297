"""The rig page says when the rig's next calibration is due (its last good calibration plus its interval, the
rule the scheduled check flags it by) and whether that date has passed."""

from datetime import timedelta

import pytest
from django.utils import timezone

from clinic.models import Calibration


@pytest.mark.django_db
def test_the_rig_page_gives_the_next_calibration_date_and_flags_it_overdue(client, charlie, olga, small_rig):
    rig, _ = small_rig
    client.force_login(charlie)
    html = client.get(f"/rigs/{rig.serial}/").content.decode()
    assert "Never calibrated" in html

    calibrated = timezone.now() - timedelta(days=10)
    Calibration.objects.create(rig=rig, calibrated_at=calibrated)
    due = client.get(f"/rigs/{rig.serial}/").context["calibration_due"]
    assert due["due"] == calibrated + timedelta(days=rig.recalibration_interval_days) and not due["overdue"]
    html = client.get(f"/rigs/{rig.serial}/").content.decode()
    assert f"Next calibration due on <strong>{due['due']:%-d %b %Y}</strong> (in 20 days)" in html

    rig.recalibration_interval_days = 7  # the same calibration, a shorter interval: three days late
    rig.save(update_fields=["recalibration_interval_days"])
    html = client.get(f"/rigs/{rig.serial}/").content.decode()
    assert "Calibration overdue" in html and "(3 days ago)" in html

    client.force_login(olga)  # another clinic's rig is not there
    assert client.get(f"/rigs/{rig.serial}/").status_code == 404
