"""The clinic service benchmark runs at main: it had rotted twice unnoticed (a SECRET_KEY the settings refuse,
the HTTPS redirect on loopback) because nothing ran it between paper-scale runs.

Upload and polling only (``--jobs 0``) on the tiny scenario, against the real PostgreSQL and gunicorn; the
figures themselves belong to ``docs/benchmarks.md``, not to a test.
"""

import json
import os
import sys
from pathlib import Path

import psycopg

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_service  # noqa: E402
from tests.services import require_postgres, require_redis  # noqa: E402


def test_it_uploads_and_polls_a_tiny_capture(torso_scenario, tmp_path):
    require_redis()
    require_postgres("postgres")
    out = tmp_path / "service.json"
    db = f"torsoscan_bench_test_{os.getpid()}"
    try:
        bench_service.main(["--scenario", str(torso_scenario), "--jobs", "0", "--poll-seconds", "1",
                            "--database", db, "--out", str(out)])
    finally:
        with psycopg.connect(dbname="postgres", host="127.0.0.1", user="postgres", autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{db}" WITH (FORCE)')
    result = json.loads(out.read_text())
    assert result["upload"]["images"] == 20
    assert result["upload"]["megabytes_per_second"] > 0
    assert all(rate > 0 for rate in result["polling_requests_per_second"].values())
    assert all(mib > 0 for mib in result["upload"]["peak_rss_mib"].values())
    assert result["commit"] and result["machine"]
