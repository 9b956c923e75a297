"""Service tests that break things: a Redis of the test's own (stopped and started again), and the clinic's
processes on PostgreSQL (a web server, a worker that may be killed and started again).

Built from the helpers of ``service_flow`` and ``test_service_flow_postgres``.
The system's Redis (6379) is never touched: each test runs its own on a free
loopback port, without persistence, so a restart loses whatever the broker held.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.service_flow import HttpApi, free_port, stop_processes, wait_for_port
from tests.services import require_postgres
from tests.test_service_flow_postgres import ROOT, run_manage

SEED = ("from django.contrib.auth.models import User; from clinic.models import Clinic, Member, Patient, Visit;"
        "c = Clinic.objects.create(name='Northside');"
        "u = User.objects.create_user('alice', '', 'pw-alice');"
        "Member.objects.create(clinic=c, user=u, role='administrator');"
        "p = Patient.objects.create(clinic=c, identifier='P-1', name='Test Patient');"
        "print(c.pk, Visit.objects.create(patient=p).pk)")


class OwnRedis:
    """A redis-server of the test's own on a free loopback port, which the test stops and starts again."""

    def __init__(self, folder: Path):
        if shutil.which("redis-server") is None:
            pytest.skip("redis-server is not installed")
        self.folder, self.port, self.proc = folder, free_port(), None
        folder.mkdir(parents=True, exist_ok=True)

    @property
    def url(self):
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self):
        self.proc = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", str(self.folder)], stdout=open(self.folder / "redis.log", "a"), stderr=subprocess.STDOUT)
        wait_for_port(self.port)

    def stop(self):
        """Gone at once, and what it held with it (no persistence): a broker that blinks."""
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(timeout=10)
            self.proc = None


class Clinic:
    """The clinic's processes on a fresh PostgreSQL database and a broker of the test's own."""

    def __init__(self, tmp_path: Path, broker: OwnRedis, **env):
        import psycopg

        require_postgres("postgres")
        self.dbname = f"torsoscan_outage_{os.getpid()}_{free_port()}"
        with psycopg.connect(dbname="postgres", host="127.0.0.1", user="postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{self.dbname}"')
        self.var, self.logs = tmp_path / "var", tmp_path / "logs"
        self.logs.mkdir()
        self.broker = broker
        self.env = {**os.environ, "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{self.dbname}",
                    "CELERY_BROKER_URL": broker.url, "CELERY_QUEUE": f"outage-{os.getpid()}",
                    "DJANGO_SETTINGS_MODULE": "clinic.settings", "TORSOSCAN_VAR": str(self.var),
                    "DB_CONN_MAX_AGE": "0", **env}
        run_manage(self.env, "migrate", "--noinput")
        self.clinic_id, self.visit_id = map(int, run_manage(self.env, "shell", "-c", SEED).split()[-2:])
        self.port = free_port()
        self.server = subprocess.Popen(
            [sys.executable, "manage.py", "runserver", "--noreload", f"127.0.0.1:{self.port}"], cwd=ROOT,
            env=self.env, stdout=open(self.logs / "server.log", "w"), stderr=subprocess.STDOUT)
        self.workers, self.others = [], []
        wait_for_port(self.port)
        self.api = HttpApi(f"http://127.0.0.1:{self.port}")
        self.api.login("alice", "pw-alice")

    def start_worker(self, *options):
        """A Celery worker process (prefork, two children, unless ``options`` say otherwise)."""
        n = len(self.workers)
        w = subprocess.Popen(
            [sys.executable, "-m", "celery", "-A", "clinic", "worker", "--loglevel", "info", "--without-gossip",
             "--without-mingle", "-Q", self.env["CELERY_QUEUE"], "-n", f"w{n}@%h", *(options or ("-c", "2"))],
            cwd=ROOT, env=self.env, stdout=open(self.logs / f"worker{n}.log", "w"), stderr=subprocess.STDOUT)
        self.workers.append(w)
        return w

    def start_beat(self):
        """Celery beat (the database scheduler, as in production): it runs the sweeper on its schedule."""
        beat = subprocess.Popen([sys.executable, "-m", "celery", "-A", "clinic", "beat", "--loglevel", "info"],
                                cwd=ROOT, env=self.env, stdout=open(self.logs / "beat.log", "w"),
                                stderr=subprocess.STDOUT)
        self.others.append(beat)
        return beat

    def worker_log(self) -> str:
        return "".join(p.read_text() for p in sorted(self.logs.glob("worker*.log")))

    def sweep(self, *args) -> str:
        """``manage.py dispatch_queued``, as beat runs it."""
        return run_manage(self.env, "dispatch_queued", *args)

    def sql(self, query, *params):
        import psycopg

        with psycopg.connect(dbname=self.dbname, host="127.0.0.1", user="postgres", autocommit=True) as conn:
            return conn.execute(query, params).fetchall()

    def media(self) -> Path:
        return self.var / "media"

    def close(self):
        stop_processes([self.server, *self.workers, *self.others], timeout=30)
        import psycopg

        with psycopg.connect(dbname="postgres", host="127.0.0.1", user="postgres", autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{self.dbname}" WITH (FORCE)')

    def dump_logs(self):
        for p in sorted(self.logs.glob("*.log")):
            print(f"--- {p.name}\n{p.read_text()[-4000:]}")


@contextmanager
def clinic_with_own_broker(tmp_path: Path, **env):
    """(clinic, broker): the broker started, no worker yet."""
    broker = OwnRedis(tmp_path / "redis")
    broker.start()
    clinic = None
    try:
        clinic = Clinic(tmp_path, broker, **env)
        yield clinic, broker
    except BaseException:
        if clinic is not None:
            clinic.dump_logs()
        raise
    finally:
        if clinic is not None:
            clinic.close()
        broker.stop()


def images_in_store(clinic: Clinic, manifest_folder: Path, session_id: str) -> dict:
    """Camera -> whether the stored image of the session has the manifest's sha256."""
    import hashlib

    manifest = json.loads((manifest_folder / "capture.json").read_text())
    rows = dict(clinic.sql("SELECT i.camera, i.file FROM clinic_captureimage i JOIN clinic_capturesession s "
                           "ON s.id = i.session_id WHERE s.uid = %s", session_id))
    out = {}
    for im in manifest["images"]:
        path = clinic.media() / (rows.get(im["camera"]) or "missing/none")
        out[im["camera"]] = path.is_file() and hashlib.sha256(path.read_bytes()).hexdigest() == im["sha256"]
    return out


def wait_until(predicate, timeout, what, step=0.25):
    t0 = time.time()
    while not predicate():
        assert time.time() - t0 < timeout, f"{what}: not after {timeout} s"
        time.sleep(step)
    return time.time() - t0
