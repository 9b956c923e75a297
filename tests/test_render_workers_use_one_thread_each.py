"""The simulator's render processes (one per core) run each library's pool on one thread: threads on top of the
processes only spin waiting on each other (recon_engine.parallel.start_worker_process)."""

import json
import os
import subprocess
import sys

PROBE = (
    "import json, os, numpy\n"
    "from recon_engine.parallel import start_worker_process\n"
    "start_worker_process()\n"
    "import cv2, open3d\n"
    "from threadpoolctl import threadpool_info\n"
    "print(json.dumps({'cv2': cv2.getNumThreads(), 'omp': os.environ['OMP_NUM_THREADS'],\n"
    "                  'blas': sorted({i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'})}))\n"
)


def test_a_render_worker_runs_blas_openmp_and_opencv_on_one_thread_each():
    # a caller whose libraries would use two threads each
    env = dict(os.environ, OMP_NUM_THREADS="2", OPENBLAS_NUM_THREADS="2")
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.splitlines()[-1]) == {"cv2": 1, "omp": "1", "blas": [1]}


def test_the_simulator_starts_its_render_workers_so(monkeypatch, tmp_path):
    from recon_engine import parallel
    from recon_engine.simulator import scenario
    from recon_engine.simulator.config import preset

    pools = []

    class Pool:
        def __init__(self, n, mp_context=None, initializer=None):
            pools.append(initializer)

        def shutdown(self):
            pass

    monkeypatch.setattr(scenario, "ProcessPoolExecutor", Pool)
    monkeypatch.setattr(scenario, "_simulate", lambda *a: {})
    scenario.simulate(tmp_path / "s", preset("tiny"), workers=2)
    assert pools == [parallel.start_worker_process]
