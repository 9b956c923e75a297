"""Faults injected into a running clinic; per scenario, jobs completed / lost / stuck and files orphaned / missing.

Real processes, as tests/outage.py starts them: PostgreSQL (a fresh database),
a redis-server of its own on a free port (stopped and started again), a web
server, Celery beat and workers, with short leases so a dead worker's step is
taken over quickly. The simulator's tiny rig is calibrated once; then each
scenario uploads the torso capture again (a new Idempotency-Key) and breaks
something while it is handled:

- the broker stopped during the finalize (started again 3 s later);
- the broker stopped during a bundle upload (the same);
- the worker (a single process) SIGKILLed during an arm, a new one started;
- one pool child of a prefork worker SIGKILLed during an arm (the main process lives);
- the same two kills during the registration, and during the analysis (indices and pictures);
- every database connection terminated (pg_terminate_backend) during an arm.

A registration killed half-way has stored some of its files (the torso, some
pictures, a comparison's map) before its rows name them; the attempt that
takes it over removes them, so a scenario counts orphans after its job ends.

A job is completed when it succeeded with one reconstruction, lost when it
failed or never existed, stuck when it had not finished after ``--timeout``.
Files are counted by ``manage.py check_files --grace-minutes 0`` after each
scenario (no upload in flight then): orphaned (no row names them) and missing
(a row names them, the store has none).

    make faults          # or: .venv/bin/python benchmarks/bench_faults.py [--scenario DIR] [--timeout S]
"""

import argparse
import io
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import uuid
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.outage import Clinic, OwnRedis, clinic_with_own_broker  # noqa: E402
from tests.service_flow import calibrate_set, register_rig  # noqa: E402
from tests.test_service_flow_postgres import run_manage  # noqa: E402

LEASE, SWEEP, REDISPATCH = 8, 2, 10
# plain HTTP on loopback, as the tests run it (with DEBUG off the settings want HTTPS and a real SECRET_KEY)
os.environ.setdefault("DEBUG", "true")


def simulate_tiny(out: Path) -> Path:
    """The tests' tiny installation: 3 test-field poses and one torso capture (visit0-a)."""
    from recon_engine.simulator.config import preset
    from recon_engine.simulator.scenario import simulate

    if not (out / "rig.json").exists():
        simulate(out, preset("tiny", seed=11, captures=(("visit0-a", 0),), session=1), progress=lambda m: None)
    return out


def zip_folder(folder: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(folder).as_posix())
    return buf.getvalue()


class Bench:
    def __init__(self, clinic: Clinic, broker: OwnRedis, scenario: Path, timeout: float):
        self.clinic, self.broker, self.api, self.timeout = clinic, broker, clinic.api, timeout
        self.capture = scenario / "captures" / "visit0-a"
        self.manifest = json.loads((self.capture / "capture.json").read_text())
        self.key = register_rig(self.api, clinic.clinic_id, scenario)
        assert calibrate_set(self.api, self.key, scenario, "faults")["state"] == "succeeded", "calibration failed"

    # --- a capture, image by image or as a bundle --------------------------------------------------------------

    def open_session(self) -> str:
        r = self.api.call("POST", "/api/sessions", key=self.key, headers={"Idempotency-Key": uuid.uuid4().hex},
                          json_body={"manifest": self.manifest, "visit": self.clinic.visit_id})
        assert r.status == 201, r.content
        sid = r.json()["id"]
        for im in self.manifest["images"]:
            r = self.api.call("PUT", f"/api/sessions/{sid}/images/{im['camera']}", key=self.key,
                              data=(self.capture / im["file"]).read_bytes())
            assert r.status == 201, r.content
        return sid

    def finalize(self, sid: str) -> str:
        """The job of the finalized session (retried as a rig would on a 503)."""
        for _ in range(20):
            r = self.api.call("POST", f"/api/sessions/{sid}/finalize", key=self.key)
            if r.status != 503:
                break
            time.sleep(1)
        if r.status == 409:  # the first attempt's answer was lost: it finalized
            r = self.api.call("GET", f"/api/sessions/{sid}", key=self.key)
        assert r.status == 200, (r.status, r.content[:300])
        return r.json()["jobs"][0]["id"]

    def upload(self) -> str:
        return self.finalize(self.open_session())

    def upload_bundle(self) -> str:
        data, key = zip_folder(self.capture), uuid.uuid4().hex
        for _ in range(20):
            r = self.api.call("POST", f"/api/bundles?visit={self.clinic.visit_id}", data=data, key=self.key,
                              content_type="application/zip", headers={"Idempotency-Key": key})
            if r.status != 503:
                break
            time.sleep(1)
        assert r.status in (200, 201), (r.status, r.content[:300])
        return r.json()["jobs"][0]["id"]

    # --- what happened ---------------------------------------------------------------------------------------------

    def wait_arm_running(self, job: str):
        t0 = time.time()
        q = ("SELECT count(*) FROM clinic_armtask a JOIN clinic_job j ON j.id = a.job_id "
             "WHERE j.uid = %s AND a.state = 'running'")
        while not self.clinic.sql(q, job)[0][0]:
            if time.time() - t0 > self.timeout:
                raise TimeoutError(f"job {job}: no arm running after {self.timeout} s")
            time.sleep(0.2)

    def wait_stage(self, job: str, stage: str):
        """Until the job's row says it is in ``stage`` (polled every 50 ms: the tiny rig's steps are short)."""
        t0 = time.time()
        while self.clinic.sql("SELECT stage FROM clinic_job WHERE uid = %s", job) != [(stage,)]:
            if time.time() - t0 > self.timeout:
                raise TimeoutError(f"job {job}: not at {stage!r} after {self.timeout} s")
            time.sleep(0.05)

    def outcome(self, name: str, jobs: list, t0: float) -> dict:
        deadline = t0 + self.timeout
        states = {}
        for job in jobs:
            while True:
                state = self.clinic.sql("SELECT state FROM clinic_job WHERE uid = %s", job)
                state = state[0][0] if state else "lost"
                if state in ("succeeded", "failed", "lost") or time.time() > deadline:
                    break
                time.sleep(0.5)
            recs = self.clinic.sql("SELECT count(*) FROM clinic_reconstruction r JOIN clinic_job j "
                                   "ON j.id = r.job_id WHERE j.uid = %s", job)[0][0]
            states[job] = "completed" if state == "succeeded" and recs == 1 else \
                "stuck" if state in ("queued", "running") else "lost"
        files = self.check_files()
        return {"scenario": name, "completed": list(states.values()).count("completed"),
                "lost": list(states.values()).count("lost"), "stuck": list(states.values()).count("stuck"),
                **files, "seconds": round(time.time() - t0, 1)}

    def check_files(self) -> dict:
        r = subprocess.run([sys.executable, "manage.py", "check_files", "--grace-minutes", "0"], cwd=ROOT,
                           env=self.clinic.env, capture_output=True, text=True, timeout=300)
        m = re.search(r"(\d+) orphaned .* (\d+) rows' files missing", r.stdout)
        assert m, f"check_files said: {r.stdout[-500:]} {r.stderr[-2000:]}"
        return {"orphaned": int(m.group(1)), "missing": int(m.group(2))}

    # --- the scenarios ---------------------------------------------------------------------------------------------

    def broker_down_during_finalize(self):
        sid = self.open_session()
        t0 = time.time()
        self.broker.stop()
        job = self.finalize(sid)
        time.sleep(3)
        self.broker.start()
        return self.outcome("broker stopped during finalize", [job], t0)

    def broker_down_during_bundle(self):
        t0 = time.time()
        self.broker.stop()
        job = self.upload_bundle()
        time.sleep(3)
        self.broker.start()
        return self.outcome("broker stopped during a bundle upload", [job], t0)

    def worker_killed_during_arm(self, prefork):
        stop(prefork)
        solo = self.clinic.start_worker("--pool", "solo")
        t0 = time.time()
        job = self.upload()
        self.wait_arm_running(job)
        os.kill(solo.pid, signal.SIGKILL)
        solo.wait(timeout=10)
        replacement = self.clinic.start_worker("-c", "2")
        return self.outcome("worker SIGKILLed during an arm", [job], t0), replacement

    def pool_child_killed_during_arm(self, prefork):
        t0 = time.time()
        job = self.upload()
        self.wait_arm_running(job)
        children = Path(f"/proc/{prefork.pid}/task/{prefork.pid}/children").read_text().split()
        os.kill(int(children[0]), signal.SIGKILL)
        return self.outcome("pool child SIGKILLed during an arm", [job], t0)

    def worker_killed_during(self, stage, prefork):
        """A single-process worker SIGKILLed while the job is at ``stage``; a new prefork worker takes over."""
        stop(prefork)
        solo = self.clinic.start_worker("--pool", "solo")
        t0 = time.time()
        job = self.upload()
        self.wait_stage(job, stage)
        os.kill(solo.pid, signal.SIGKILL)
        solo.wait(timeout=10)
        replacement = self.clinic.start_worker("-c", "2")
        return self.outcome(f"worker SIGKILLed during the {STAGE_NAMES[stage]}", [job], t0), replacement

    def pool_child_killed_during(self, stage, prefork):
        """The pool child doing the step SIGKILLed (a prefork worker of one child; its main process lives)."""
        stop(prefork)
        single = self.clinic.start_worker("-c", "1")
        t0 = time.time()
        job = self.upload()
        self.wait_stage(job, stage)
        children = Path(f"/proc/{single.pid}/task/{single.pid}/children").read_text().split()
        os.kill(int(children[0]), signal.SIGKILL)
        out = self.outcome(f"pool child SIGKILLed during the {STAGE_NAMES[stage]}", [job], t0)
        stop(single)
        return out, self.clinic.start_worker("-c", "2")

    def db_connections_terminated(self):
        t0 = time.time()
        job = self.upload()
        self.wait_arm_running(job)
        import psycopg

        with psycopg.connect(dbname="postgres", host="127.0.0.1", user="postgres", autocommit=True) as conn:
            killed = conn.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s "
                                  "AND pid <> pg_backend_pid()", (self.clinic.dbname,)).fetchall()
        out = self.outcome("DB connections terminated during an arm", [job], t0)
        out["connections killed"] = len(killed)
        return out


# the job's stage while each step runs (clinic/pipeline.py)
STAGE_NAMES = {"registration": "registration", "indices and pictures": "analysis"}
KILLS_IN_STAGES = {f"{who}_killed_during_{name}": (who, stage) for stage, name in STAGE_NAMES.items()
                   for who in ("worker", "pool_child")}
STEPS = ["broker_down_during_finalize", "broker_down_during_bundle", "worker_killed_during_arm",
         "pool_child_killed_during_arm", *KILLS_IN_STAGES, "db_connections_terminated"]


def stop(proc):
    proc.terminate()
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", type=Path, help="a tiny scenario (default: simulated into --work)")
    parser.add_argument("--work", type=Path, default=ROOT / "bench-out" / "faults")
    parser.add_argument("--timeout", type=float, default=600, help="a job not finished by then is stuck (s)")
    parser.add_argument("--only", nargs="+", choices=STEPS, default=STEPS, help="run only these scenarios")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    t_sim = time.time()
    scenario = args.scenario or simulate_tiny(args.work / "scenario")
    print(f"scenario {scenario} ({time.time() - t_sim:.0f} s)", flush=True)
    run = Path(tempfile.mkdtemp(prefix="run-", dir=args.work))
    results = []
    with clinic_with_own_broker(run, JOB_LEASE_SECONDS=str(LEASE), JOB_SWEEP_SECONDS=str(SWEEP),
                                JOB_REDISPATCH_SECONDS=str(REDISPATCH)) as (clinic, broker):
        prefork = clinic.start_worker("-c", "2")
        clinic.start_beat()
        bench = Bench(clinic, broker, scenario, args.timeout)
        print(f"rig calibrated; lease {LEASE} s, sweep every {SWEEP} s, queued work re-sent after {REDISPATCH} s",
              flush=True)
        for step in args.only:
            if step == "worker_killed_during_arm":
                out, prefork = bench.worker_killed_during_arm(prefork)
            elif step == "pool_child_killed_during_arm":
                out = bench.pool_child_killed_during_arm(prefork)
            elif step in KILLS_IN_STAGES:
                who, stage = KILLS_IN_STAGES[step]
                out, prefork = getattr(bench, f"{who}_killed_during")(stage, prefork)
            else:
                out = getattr(bench, step)()
            results.append(out)
            print(json.dumps(out), flush=True)
    print(f"\n{'scenario':46} completed lost stuck orphaned missing  seconds")
    for r in results:
        print(f"{r['scenario']:46} {r['completed']:9} {r['lost']:4} {r['stuck']:5} {r['orphaned']:8} "
              f"{r['missing']:7} {r['seconds']:8}")
    bad = sum(r["lost"] + r["stuck"] + r["orphaned"] + r["missing"] for r in results)
    print("target met: zero lost, stuck, orphaned, missing" if not bad else f"TARGET MISSED ({bad})")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
