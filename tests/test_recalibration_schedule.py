"""Scheduled work: rigs due for recalibration are flagged, and their new captures carry the flag."""

from datetime import timedelta

import pytest
from django.conf import settings
from django.core.files.base import ContentFile
from django.utils import timezone

from clinic.models import Calibration, Rig
from clinic.tasks import flag_rigs_for_recalibration
from tests.api_helpers import open_session, small_bundle


@pytest.mark.django_db
def test_a_rig_whose_calibration_is_too_old_is_flagged(small_rig, tmp_path, client):
    rig, key = small_rig
    calib = Calibration.objects.create(rig=rig, calibrated_at=timezone.now() - timedelta(days=45))
    calib.file.save("c.json", ContentFile(b"{}"))
    assert flag_rigs_for_recalibration.delay().get() == ["RIG-T"]
    rig.refresh_from_db()
    assert rig.needs_recalibration and "45 days old" in rig.recalibration_reason
    body = open_session(client, key, small_bundle(tmp_path)).json()
    assert body["needs_recalibration"] and "45 days" in body["recalibration_reason"]


@pytest.mark.django_db
def test_a_recent_calibration_is_not_flagged(small_rig):
    rig, _ = small_rig
    Calibration.objects.create(rig=rig, calibrated_at=timezone.now() - timedelta(days=3))
    assert flag_rigs_for_recalibration.delay().get() == []
    assert not Rig.objects.get(pk=rig.pk).needs_recalibration


def test_the_check_is_on_the_beat_schedule():
    entry = settings.CELERY_BEAT_SCHEDULE["flag-rigs-for-recalibration"]
    assert entry["task"] == "clinic.tasks.flag_rigs_for_recalibration"
    assert settings.CELERY_BEAT_SCHEDULER.startswith("django_celery_beat")
