"""Beat runs the stored-files check (reporting only): the schedule names the task, and the task logs what is
wrong without deleting it."""

import logging

import pytest
from django.conf import settings
from django.core.files.storage import default_storage

from clinic import tasks
from tests.file_check_helpers import one_stored_image, stray_file


def test_the_beat_schedule_runs_the_file_check():
    entry = settings.CELERY_BEAT_SCHEDULE["check-stored-files"]
    assert entry["task"] == "clinic.tasks.check_files" and entry["task"] in tasks.check_files.app.tasks
    assert entry["schedule"] == 24 * 3600


@pytest.mark.django_db
def test_the_task_logs_an_orphan_and_keeps_it(client, small_rig, tmp_path, caplog):
    one_stored_image(client, small_rig[1], tmp_path)
    stray = stray_file("captures/RIG-T/incoming-89ab/images/B1.png")
    with caplog.at_level(logging.WARNING, logger="clinic.filecheck"):
        summary = tasks.check_files.delay().get()
    assert "1 orphaned (0 removed)" in summary
    assert f"stored file {stray}: no row references it" in caplog.text
    assert default_storage.exists(stray)
