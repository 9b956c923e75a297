"""A gunicorn server on a fresh PostgreSQL database of the test's own, with the small boundary rig registered.

Migrating PostgreSQL takes about 20 s on the CI machine: it is done once into a
template database (named after the migrations' checksum, so a new migration
makes a new one) and every test copies it (``CREATE DATABASE ... TEMPLATE``,
well under a second). The server runs ``tests.fault_storage.FaultStorage``:
the test arms a fault by creating a file (see there); unarmed it is the plain
file system storage.
"""

import hashlib
import os
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

from tests.service_flow import HttpApi, free_port, stop_processes, wait_for_port
from tests.services import require_postgres

ROOT = Path(__file__).resolve().parents[1]
PG = dict(host="127.0.0.1", port=5432, user="postgres")

KEY = "tsk_the-pg-server-tests-rig-key"  # the template's rig key (only its hash is stored, as for any key)
SEED = ("from django.contrib.auth.models import User;"
        "from clinic.api import sync_cameras; from clinic.models import Clinic, Member, Patient, Rig, RigKey, Visit;"
        "from clinic.models import hash_key;"
        "from recon_engine.formats import rig_from_dict; from tests.boundary_fixtures import RIG;"
        "c = Clinic.objects.create(name='Northside');"
        "u = User.objects.create_user('alice', '', 'pw-alice');"
        "Member.objects.create(clinic=c, user=u, role='administrator');"
        "rig = Rig.objects.create(clinic=c, serial=RIG['serial'], description=RIG);"
        "sync_cameras(rig, rig_from_dict(RIG));"
        "Visit.objects.create(patient=Patient.objects.create(clinic=c, identifier='P-1', name='Test Patient'));"
        f"RigKey.objects.create(rig=rig, prefix='{KEY[:10]}', key_hash=hash_key('{KEY}'))")


def run_sql(query, dbname="postgres"):
    import psycopg

    with psycopg.connect(dbname=dbname, autocommit=True, **PG) as conn:
        return conn.execute(query).fetchall() if query.lstrip().upper().startswith("SELECT") else conn.execute(query)


def run_manage(env, *args):
    r = subprocess.run([sys.executable, "manage.py", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, f"manage.py {' '.join(args)} failed: {r.stderr[-3000:]}"
    return r.stdout


def template_database(env) -> str:
    """A migrated and seeded database to copy; made once per set of migrations (under a temporary name, then
    renamed)."""
    digest = hashlib.sha256(SEED.encode())
    for p in sorted((ROOT / "clinic" / "migrations").glob("*.py")):
        digest.update(p.read_bytes())
    name = f"torsoscan_template_{digest.hexdigest()[:12]}"
    if run_sql(f"SELECT 1 FROM pg_database WHERE datname = '{name}'"):
        return name
    building = f"{name}_{os.getpid()}"
    run_sql(f'DROP DATABASE IF EXISTS "{building}"')
    run_sql(f'CREATE DATABASE "{building}"')
    env = {**env, "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{building}"}
    run_manage(env, "migrate", "--noinput")
    run_manage(env, "shell", "-c", SEED)
    try:
        run_sql(f'ALTER DATABASE "{building}" RENAME TO "{name}"')
    except Exception:  # another test made it meanwhile
        run_sql(f'DROP DATABASE IF EXISTS "{building}" WITH (FORCE)')
    return name


class Server:
    def __init__(self, tmp_path: Path, threads: int = 4, **env):
        require_postgres("postgres")
        self.var, self.logs = tmp_path / "var", tmp_path / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.dbname = f"torsoscan_pg_{os.getpid()}_{free_port()}"
        self.env = {**os.environ, "DJANGO_SETTINGS_MODULE": "clinic.settings", "TORSOSCAN_VAR": str(self.var),
                    "CELERY_BROKER_URL": "", "STORAGE_BACKEND": "tests.fault_storage.FaultStorage",
                    "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{self.dbname}", **env}
        template = template_database(self.env)
        run_sql(f'CREATE DATABASE "{self.dbname}" TEMPLATE "{template}"')
        self.key = KEY
        (self.visit_id,), = self.sql("SELECT id FROM clinic_visit")
        self.port = free_port()
        # threads, each keeping its own database connection between requests (CONN_MAX_AGE), as in production
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "gunicorn", "clinic.wsgi:application", "--bind", f"127.0.0.1:{self.port}",
             "--workers", "1", "--worker-class", "gthread", "--threads", str(threads), "--timeout", "60"],
            cwd=ROOT, env=self.env, stdout=open(self.logs / "server.log", "w"), stderr=subprocess.STDOUT)
        wait_for_port(self.port)
        self.api = HttpApi(f"http://127.0.0.1:{self.port}")

    def arm(self, fault: str):
        """Make the storage's next save do ``fault`` (tests/fault_storage.py)."""
        (self.var / f"fault-{fault}").touch()

    def media_files(self):
        media = self.var / "media"
        return sorted(str(p.relative_to(media)) for p in media.rglob("*") if p.is_file()) if media.exists() else []

    def sql(self, query):
        return run_sql(query, self.dbname)

    def terminate_connections(self) -> int:
        """Every server connection to the test's database killed, as a database restart does."""
        rows = run_sql("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                    f"WHERE datname = '{self.dbname}' AND pid <> pg_backend_pid()")
        return len(rows)

    def log(self) -> str:
        return (self.logs / "server.log").read_text()

    def close(self):
        stop_processes([self.proc], timeout=20)
        run_sql(f'DROP DATABASE IF EXISTS "{self.dbname}" WITH (FORCE)')


@contextmanager
def pg_server(tmp_path: Path, threads: int = 4, **env):
    server = Server(tmp_path, threads, **env)
    try:
        yield server
    except BaseException:
        print(server.log()[-5000:])
        raise
    finally:
        server.close()
