"""The service migrates and checks on the real PostgreSQL."""

import os
import subprocess
import sys
from pathlib import Path

from tests.services import require_postgres

ROOT = Path(__file__).resolve().parents[1]


def test_it_migrates_on_postgresql(tmp_path):
    url = require_postgres()
    env = {**os.environ, "DATABASE_URL": url, "TORSOSCAN_VAR": str(tmp_path)}
    for args in (["check", "--database", "default"], ["migrate", "--noinput"]):
        r = subprocess.run([sys.executable, "manage.py", *args], cwd=ROOT, env=env, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
