"""A broker that blinks loses no work: a finalize during the outage is answered with its job queued, the images
stay, and once the broker is back the sweeper sends the job, which runs to the end once.

Real processes: PostgreSQL, a redis-server of the test's own (stopped, and
started again empty, as a broker restarted without persistence), a web server
and a Celery worker.
"""

import os
import signal
import subprocess
import sys
import time

from django.conf import settings

from tests.outage import ROOT, OwnRedis, clinic_with_own_broker, images_in_store, wait_until
from tests.service_flow import register_rig, upload_capture, wait_for_job
from tests.test_service_flow_postgres import run_manage


def test_it_runs_a_calibration_finalized_while_the_broker_was_down(tmp_path, rig_session_1):
    with clinic_with_own_broker(tmp_path) as (clinic, broker):
        clinic.start_worker()
        api = clinic.api
        key = register_rig(api, clinic.clinic_id, rig_session_1)
        poses = sorted((rig_session_1 / "captures").glob("testfield-pose*"))

        broker.stop()
        t0 = time.time()
        # every request succeeds (upload_capture asserts 201 for the session and each image, 200 for finalize)
        sessions = [upload_capture(api, key, folder, calibration_set="outage", poses=len(poses)) for folder in poses]
        upload_seconds = time.time() - t0
        jobs = [j for j in sessions[-1]["jobs"] if j["kind"] == "calibration"]
        assert len(jobs) == 1 and jobs[0]["state"] == "queued", sessions[-1]["jobs"]
        job_id = jobs[0]["id"]
        for folder, session in zip(poses, sessions):
            assert all(images_in_store(clinic, folder, session["id"]).values())
        assert "could not send clinic.tasks.run_calibration" in (clinic.logs / "server.log").read_text()

        # the sweeper itself survives the outage: nothing sent, the job still queued
        assert "0 step(s) re-dispatched" in clinic.sweep("--older-than", "0")
        assert api.call("GET", f"/api/jobs/{job_id}", key=key).json()["state"] == "queued"
        # so does a re-run asked for by staff: answered, the job still queued
        r = api.call("POST", f"/api/jobs/{job_id}/rerun")
        assert r.status == 200 and r.json()["state"] == "queued", r.content

        broker.start()
        back = time.time()
        # the web server's own connection recovers: a new upload is sent at once, without a sweep (a torso,
        # failed at once: the rig has no calibration yet; the calibration is still queued)
        torso = upload_capture(api, key, rig_session_1 / "captures" / "visit0-a", visit=clinic.visit_id)
        failed = wait_for_job(api, key, torso["jobs"][0]["id"], timeout=120)
        assert failed["state"] == "failed" and "no calibration" in failed["error"], failed
        torso_after = time.time() - back
        assert api.call("GET", f"/api/jobs/{job_id}", key=key).json()["state"] == "queued"

        # the sweep sends the calibration; a duplicate delivery (a second sweep, a redelivery) is refused
        swept = time.time()
        assert "1 step(s) re-dispatched" in clinic.sweep("--older-than", "0")
        (pk,), = clinic.sql("SELECT id FROM clinic_job WHERE uid = %s", job_id)
        run_manage(clinic.env, "shell", "-c", f"from clinic.tasks import run_calibration; run_calibration.delay({pk})")
        job = wait_for_job(api, key, job_id, timeout=300)
        done_after = time.time() - swept
        assert job["state"] == "succeeded" and job["attempt"] == 1, job
        assert clinic.sql("SELECT count(*) FROM clinic_calibration") == [(1,)]
        wait_until(lambda: "'not claimed'" in clinic.worker_log(), 30, "the second delivery refused")
        # and nothing is left to send
        assert "0 step(s) re-dispatched" in clinic.sweep("--older-than", "0")
        (started,), = clinic.sql("SELECT extract(epoch from started) FROM clinic_job WHERE kind = 'calibration'")
        print(f"uploads during the outage {upload_seconds:.1f} s; once the broker was back, a new upload's job "
              f"ran {torso_after:.1f} s later; after the sweep, the calibration was claimed in "
              f"{float(started) - swept:.1f} s and done in {done_after:.1f} s")


def test_the_sweeper_is_on_the_beat_schedule():
    entry = settings.CELERY_BEAT_SCHEDULE["redispatch-stalled-jobs"]
    assert entry["task"] == "clinic.tasks.redispatch_stalled" and entry["schedule"] == settings.JOB_SWEEP_SECONDS
    # at least one sweep per period, or a step would wait longer than JOB_REDISPATCH_SECONDS to be sent again
    assert settings.JOB_SWEEP_SECONDS <= settings.JOB_REDISPATCH_SECONDS


def test_it_gives_up_on_a_broker_that_does_not_answer(tmp_path):
    # a hung Redis (stopped: connections are accepted, nothing is answered) must not hold a request
    broker = OwnRedis(tmp_path / "redis")
    broker.start()
    broker.proc.send_signal(signal.SIGSTOP)
    try:
        code = ("import time, django; django.setup(); from clinic import pipeline, tasks; t = time.time(); "
                "print(pipeline.send(tasks.ping), round(time.time() - t, 1))")
        env = {**os.environ, "CELERY_BROKER_URL": broker.url, "DJANGO_SETTINGS_MODULE": "clinic.settings",
               "TORSOSCAN_VAR": str(tmp_path / "var")}
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                             timeout=120)
        sent, seconds = out.stdout.split()[-2:]
        assert sent == "False" and float(seconds) < 15, out.stdout + out.stderr[-2000:]
    finally:
        broker.proc.send_signal(signal.SIGCONT)
        broker.stop()
