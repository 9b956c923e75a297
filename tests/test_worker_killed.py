"""A worker killed (SIGKILL) during an arm loses nothing: the arm's lease lapses, beat's sweeper sends it again,
a new worker takes it over and the job completes, once, within the lease's bound.

Real processes: PostgreSQL, a redis-server of the test's own, a web server,
Celery beat and workers (the first, a single process, is killed mid-arm).
Short leases (``JOB_LEASE_SECONDS``) and sweeps keep it quick.
"""

import os
import signal
import time

from tests.outage import clinic_with_own_broker, wait_until
from tests.service_flow import calibrate_set, register_rig, upload_capture, wait_for_job

LEASE, SWEEP = 6, 2


def test_it_completes_a_torso_whose_worker_was_killed_during_an_arm(tmp_path, rig_session_1):
    env = {"JOB_LEASE_SECONDS": str(LEASE), "JOB_SWEEP_SECONDS": str(SWEEP), "JOB_REDISPATCH_SECONDS": "30"}
    with clinic_with_own_broker(tmp_path, **env) as (clinic, broker):
        first = clinic.start_worker("--pool", "solo")
        clinic.start_beat()
        api = clinic.api
        key = register_rig(api, clinic.clinic_id, rig_session_1)
        assert calibrate_set(api, key, rig_session_1, "s")["state"] == "succeeded"

        session = upload_capture(api, key, rig_session_1 / "captures" / "visit0-a", visit=clinic.visit_id)
        job_id = session["jobs"][0]["id"]
        running = "SELECT a.arm FROM clinic_armtask a JOIN clinic_job j ON j.id = a.job_id " \
                  "WHERE j.uid = %s AND a.state = 'running'"
        wait_until(lambda: clinic.sql(running, job_id), 120, "an arm running")
        os.kill(first.pid, signal.SIGKILL)
        killed = time.time()
        first.wait(timeout=10)
        lease = "SELECT a.arm, extract(epoch from a.lease_until), extract(epoch from a.claimed) " \
                "FROM clinic_armtask a JOIN clinic_job j ON j.id = a.job_id WHERE j.uid = %s AND a.arm = %s"
        (killed_arm,), = clinic.sql(running, job_id)  # the dead worker's claim is left behind
        (_, lapses, _), = clinic.sql(lease, job_id, killed_arm)

        clinic.start_worker("-c", "2")
        job = wait_for_job(api, key, job_id, timeout=300)
        took = time.time() - killed
        assert job["state"] == "succeeded" and job["attempt"] == 1, job
        assert job["arms"] == {arm: {"state": "succeeded", "error": ""} for arm in "ABCD"}
        assert clinic.sql("SELECT count(*) FROM clinic_reconstruction") == [(1,)]
        assert "Sending due task redispatch-stalled-jobs" in (clinic.logs / "beat.log").read_text()
        # the killed arm was taken over after its lease lapsed (not before); a sweep after it, once a worker
        # slot was free (the sweep and the arm wait behind the other arms on a busy machine)
        (_, _, retaken), = clinic.sql(lease, job_id, killed_arm)
        assert lapses <= float(retaken) <= float(lapses) + 60
        assert "re-dispatching clinic.tasks.reconstruct_arm(" in clinic.worker_log()
        print(f"worker killed during arm {killed_arm}; its lease lapsed {float(lapses) - killed:.1f} s later, "
              f"the arm was taken over {float(retaken) - killed:.1f} s and the job done {took:.1f} s after "
              f"the kill (lease {LEASE} s, sweep every {SWEEP} s)")
