"""The whole flow through the HTTP API against the real PostgreSQL and Redis, with a real Celery worker.

The server and the worker are separate processes started by the test, as in
production: the web process only records and dispatches, the worker runs the
engine; they share the database, the broker and the media folder.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.service_flow import (HttpApi, assert_same_as_engine, free_port, register_rig, run_flow,
                                stop_processes, wait_for_port)
from tests.services import require_postgres, require_redis

ROOT = Path(__file__).resolve().parents[1]


def run_manage(env, *args, **kw):
    r = subprocess.run([sys.executable, "manage.py", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=300, **kw)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout


@pytest.fixture
def services(tmp_path):
    """A fresh PostgreSQL database, a Redis queue of its own, a server and a worker; the base URL."""
    import psycopg

    redis_url = require_redis()
    dbname = f"torsoscan_flow_{os.getpid()}"
    require_postgres("postgres")
    with psycopg.connect(dbname="postgres", host="127.0.0.1", user="postgres", autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{dbname}"')
        conn.execute(f'CREATE DATABASE "{dbname}"')
    env = {**os.environ, "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{dbname}",
           "CELERY_BROKER_URL": redis_url, "CELERY_QUEUE": f"flow-{os.getpid()}",
           "DJANGO_SETTINGS_MODULE": "clinic.settings", "TORSOSCAN_VAR": str(tmp_path / "var"),
           "DB_CONN_MAX_AGE": "0"}
    run_manage(env, "migrate", "--noinput")
    run_manage(env, "shell", "-c",
            "from django.contrib.auth.models import User; from clinic.models import Clinic, Member, Patient, Visit;"
            "c = Clinic.objects.create(name='Northside');"
            "u = User.objects.create_user('alice', '', 'pw-alice');"
            "Member.objects.create(clinic=c, user=u, role='technician');"
            "p = Patient.objects.create(clinic=c, identifier='P-1', name='Test Patient');"
            "print(c.pk, Visit.objects.create(patient=p).pk)")
    port = free_port()
    logs = tmp_path / "logs"
    logs.mkdir()
    procs = [
        subprocess.Popen([sys.executable, "manage.py", "runserver", "--noreload", f"127.0.0.1:{port}"], cwd=ROOT,
                         env=env, stdout=open(logs / "server.log", "w"), stderr=subprocess.STDOUT),
        subprocess.Popen([sys.executable, "-m", "celery", "-A", "clinic", "worker", "--concurrency", "2",
                          "--loglevel", "info", "--without-gossip", "--without-mingle", "-Q", env["CELERY_QUEUE"]],
                         cwd=ROOT, env=env, stdout=open(logs / "worker.log", "w"), stderr=subprocess.STDOUT),
    ]
    try:
        wait_for_port(port)
        yield f"http://127.0.0.1:{port}", logs
    finally:
        stop_processes(procs, timeout=30)
        with psycopg.connect(dbname="postgres", host="127.0.0.1", user="postgres", autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{dbname}" WITH (FORCE)')


def test_the_whole_flow_runs_on_postgresql_redis_and_a_worker(services, rig_session_1, rig_session_2, tmp_path):
    base, logs = services
    api = HttpApi(base)
    api.login("alice", "pw-alice")
    key = register_rig(api, 1, rig_session_1)
    try:
        steps = run_flow(api, key, rig_session_1, rig_session_2, 1, tmp_path / "out")
    except AssertionError:
        print((logs / "worker.log").read_text()[-5000:])
        print((logs / "server.log").read_text()[-3000:])
        raise
    assert steps["torso_job"]["state"] == "succeeded"
    # the arms ran as separate tasks on the worker (a group), then the registration
    worker_log = (logs / "worker.log").read_text()
    assert worker_log.count("clinic.tasks.reconstruct_arm") >= 4 and "clinic.tasks.register" in worker_log
    assert_same_as_engine(tmp_path / "out", rig_session_1)
