"""The last two test-field poses of a set, finalized at the same moment, start its calibration once.

On PostgreSQL each finalizing transaction saw only its own pose (the other's was not committed yet), so both
counted the set as incomplete and nothing ever calibrated it; the rig's row is now locked first. SQLite
serialises writers, so the race is measured on PostgreSQL: the outer test runs the inner one in a pytest of
its own whose Django database is PostgreSQL.
"""
import os
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import pytest
from django.db import connection

from clinic.models import CaptureSession, Job
from tests.api_helpers import auth, image_bytes, open_session, put, small_bundle
from tests.boundary_fixtures import image
from tests.services import require_postgres

ROOT = Path(__file__).resolve().parents[1]


def test_it_starts_one_calibration_on_postgresql():
    url = require_postgres("postgres")  # the server's own database: pytest-django makes and drops its test_ copy
    base = url.rsplit("/", 1)[0]
    env = {**os.environ, "DATABASE_URL": f"{base}/torsoscan_race_{uuid.uuid4().hex[:8]}", "RACE_ON_POSTGRES": "1"}
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
                          f"{Path(__file__).relative_to(ROOT)}::test_inner_two_poses_at_once"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "1 passed" in run.stdout, run.stdout[-3000:] + run.stderr[-2000:]


@pytest.mark.django_db(transaction=True)
def test_inner_two_poses_at_once(client, small_rig, tmp_path, monkeypatch):
    if not os.environ.get("RACE_ON_POSTGRES"):
        pytest.skip("run by test_it_starts_one_calibration_on_postgresql")
    assert connection.vendor == "postgresql"
    from clinic import pipeline

    monkeypatch.setattr(pipeline, "send", lambda task, *args: True)  # the job's row is what counts here
    _, key = small_rig
    sids = []
    for pose in (0, 1):
        folder = small_bundle(tmp_path, f"pose{pose}", kind="testfield", pose=pose, images={"A1": image(50 + pose)})
        sid = open_session(client, key, folder, poses=2).json()["id"]
        for cam in ("A1", "A2", "B1"):
            assert put(client, key, sid, cam, image_bytes(folder, cam)).status_code == 201
        sids.append(sid)
    barrier = threading.Barrier(2, timeout=20)
    save = CaptureSession.save

    def finalized_then_wait(self, *args, **kwargs):
        save(self, *args, **kwargs)
        if "finalized" in (kwargs.get("update_fields") or ()):
            # both requests are past their own session's update, neither has committed yet
            try:
                barrier.wait(timeout=5)
            except threading.BrokenBarrierError:
                pass

    monkeypatch.setattr(CaptureSession, "save", finalized_then_wait)
    answers = []

    def finalize(sid):
        try:
            answers.append(client.post(f"/api/sessions/{sid}/finalize", **auth(key)).status_code)
        finally:
            connection.close()

    threads = [threading.Thread(target=finalize, args=(sid,)) for sid in sids]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert answers == [200, 200]
    assert list(CaptureSession.objects.filter(uid__in=sids).values_list("state", flat=True)) == ["finalized"] * 2
    assert Job.objects.filter(kind=Job.CALIBRATION).count() == 1
