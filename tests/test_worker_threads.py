"""A worker's arm tasks share the cores out: concurrent tasks × threads ≤ cores (issue 29, item 3).

The engine changes no process-wide setting itself; the worker's start sets
each pool process's share (environment, OpenCV, BLAS/OpenMP through
threadpoolctl) and the arm task holds to it.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
from threadpoolctl import threadpool_info

from clinic import celery as worker
from clinic import pipeline, tasks
from recon_engine.parallel import THREAD_ENV, cores

ENV = (worker.TASK_THREADS_ENV, *THREAD_ENV)


@pytest.fixture
def worker_env(monkeypatch):
    """os.environ restored after the test, whatever the worker's start wrote into it."""
    for k in ENV:
        monkeypatch.setenv(k, "unset")
        monkeypatch.delenv(k)


def test_concurrent_tasks_times_threads_fit_the_cores():
    for cpus, concurrency, n in ((2, 2, 1), (8, 2, 4), (8, 3, 2), (2, 4, 1), (4, 1, 4)):
        assert worker.task_threads(concurrency, cpus) == n
        assert concurrency * n <= cpus or n == 1


def test_no_limit_outside_a_worker(worker_env):
    # in-process jobs (the embedded default) run one at a time: they keep every core
    assert worker.task_threads() is None
    before = cv2.getNumThreads()
    cv2.setNumThreads(3)
    try:
        with worker.task_thread_limits():
            assert cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(before)


def test_an_arm_task_runs_with_the_workers_share_of_the_cores(worker_env, monkeypatch):
    # what the worker's start leaves a pool process (see the next test): one thread per task
    monkeypatch.setenv(worker.TASK_THREADS_ENV, "1")
    monkeypatch.setenv("TORSOSCAN_THREADS", "1")
    cv_before = cv2.getNumThreads()
    blas_before = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    seen = {}

    def probe(job_id, arm):
        seen["cv2"] = cv2.getNumThreads()
        seen["blas"] = {i["num_threads"] for i in threadpool_info() if i["user_api"] in ("blas", "openmp")}
        seen["engine"] = cores()
        return "arm done"

    monkeypatch.setattr(pipeline, "reconstruct_arm", probe)
    assert tasks.reconstruct_arm(1, "A") == "arm done"
    assert seen == {"cv2": 1, "blas": {1}, "engine": 1}
    # and the task left the process's pools as they were
    assert cv2.getNumThreads() == cv_before
    assert [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"] == blas_before


def test_a_prefork_workers_pool_processes_get_their_share():
    # in a fresh process (the limits last for its lifetime), as a prefork worker with one pool process per core:
    # the main process loads numpy's and scipy's BLAS and OpenCV and starts; a pool process forks and starts
    probe = (
        "import os, json, sys, cv2, numpy, scipy.linalg\n"
        "from types import SimpleNamespace\n"
        "from threadpoolctl import threadpool_info\n"
        "from clinic import celery as worker\n"
        "worker.share_cores_out(SimpleNamespace(concurrency=os.cpu_count()))\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    worker.limit_pool_process_threads()\n"
        "    print(json.dumps([cv2.getNumThreads(), sorted({i['num_threads'] for i in threadpool_info()}),"
        " os.environ['OMP_NUM_THREADS'], os.environ['TORSOSCAN_THREADS']]), flush=True)\n"
        "    os._exit(0)\n"
        "sys.exit(os.waitpid(pid, 0)[1])\n")
    env = {**os.environ, "DJANGO_SETTINGS_MODULE": "clinic.settings"}
    for k in (worker.TASK_THREADS_ENV, *THREAD_ENV):
        env.pop(k, None)
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=300,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [1, [1], "1", "1"]
