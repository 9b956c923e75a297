"""The Celery application. Without ``CELERY_BROKER_URL`` tasks run in-process (eager).

A worker shares its cores out among the tasks it runs side by side: each of
``--concurrency`` pool processes gets ``cores // concurrency`` threads (at
least 1) for BLAS, OpenMP, OpenCV and the engine's own thread pools, so that
two arm tasks on a 2-core machine do not each start two threads per stage.
The engine sets none of this itself (a library call must not change its
caller's process); the worker, whose processes these are, does.
"""

import os
from contextlib import contextmanager

from celery import Celery, signals

# the engine's one mechanism for a process's thread pools
from recon_engine.parallel import limit_process_threads, set_opencv_threads

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "clinic.settings")

app = Celery("torsoscan")
app.config_from_object("django.conf:settings", namespace="CELERY")
app.autodiscover_tasks()

TASK_THREADS_ENV = "TORSOSCAN_TASK_THREADS"  # set by the worker's start for its pool processes


def task_threads(concurrency: int | None = None, cpus: int | None = None) -> int | None:
    """Threads one task may use: ``cpus`` (default: this machine's cores) shared out among ``concurrency`` tasks
    running side by side, at least 1. Without ``concurrency``: what the worker's start set for its pool
    processes, or None outside a worker (in-process jobs, one at a time: no limit)."""
    cpus = cpus or os.cpu_count() or 1
    if concurrency is None:
        value = os.environ.get(TASK_THREADS_ENV, "").strip()
        return int(value) if value.isdigit() and int(value) > 0 else None
    return max(1, cpus // max(1, int(concurrency)))


@contextmanager
def task_thread_limits(n: int | None = None):
    """Within: BLAS and OpenMP (threadpoolctl, if installed) and OpenCV at most ``n`` threads (default: the
    worker's share, see :func:`task_threads`), restored on leaving; nothing outside a worker.

    The pool process was limited at its start; this holds a task to its share
    also for libraries loaded since (the engine's are imported by the first
    task), and leaves the process as it found it.
    """
    n = n or task_threads()
    if not n:
        yield
        return
    before = set_opencv_threads(n)
    try:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:
            yield
        else:
            with threadpool_limits(limits=n):
                yield
    finally:
        set_opencv_threads(before)


@signals.worker_init.connect
def share_cores_out(sender=None, **kwargs):
    """The worker's main process, before its pool starts: each pool process's share of the cores, in the
    environment its pool processes inherit (libraries read it when they load)."""
    concurrency = getattr(sender, "concurrency", None) or os.cpu_count() or 1  # Celery's default: one per core
    n = task_threads(concurrency)
    os.environ[TASK_THREADS_ENV] = str(n)
    # here too, before any fork: the pool processes inherit OpenCV's setting and need not reconfigure its pool
    limit_process_threads(n)


@signals.worker_process_init.connect
def limit_pool_process_threads(**kwargs):
    """A pool process at its start: the libraries its parent loaded before forking keep their thread pools, so
    they are limited in place."""
    n = task_threads()
    if n:
        limit_process_threads(n)
