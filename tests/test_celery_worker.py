"""A real Celery worker process on the real Redis broker runs a task."""

import os
import subprocess
import sys
import time
from pathlib import Path

from tests.services import require_redis

ROOT = Path(__file__).resolve().parents[1]


def test_a_real_worker_runs_a_task_from_redis(tmp_path):
    url = require_redis()
    env = {**os.environ, "CELERY_BROKER_URL": url, "CELERY_RESULT_BACKEND": url,
           "DJANGO_SETTINGS_MODULE": "clinic.settings", "TORSOSCAN_VAR": str(tmp_path)}
    worker = subprocess.Popen(
        [sys.executable, "-m", "celery", "-A", "clinic", "worker", "--pool", "solo", "--concurrency", "1",
         "--loglevel", "warning", "--without-gossip", "--without-mingle", "--without-heartbeat",
         "-Q", f"test-{os.getpid()}"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        client = (
            "import django; django.setup()\n"
            "from clinic.tasks import ping\n"
            f"print(ping.apply_async(queue='test-{os.getpid()}').get(timeout=60))\n")
        out = subprocess.run([sys.executable, "-c", client], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip().endswith("pong")
    finally:
        worker.terminate()
        try:
            worker.wait(timeout=20)
        except subprocess.TimeoutExpired:
            worker.kill()
        time.sleep(0.1)
