"""How many threads or processes the engine's stages use."""

from __future__ import annotations

import os


THREADS_ENV = "TORSOSCAN_THREADS"


def cores(requested: int = 0) -> int:
    """``requested`` when positive, else the threads this process may use: ``TORSOSCAN_THREADS`` where set (a
    service that runs several engine jobs side by side shares the cores out so), else one per core."""
    if requested > 0:
        return requested
    budget = os.environ.get(THREADS_ENV, "").strip()
    if budget.isdigit() and int(budget) > 0:
        return int(budget)
    return os.cpu_count() or 1


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)


def _libc():
    """The C library (ctypes); OSError where there is none to load."""
    import ctypes
    import ctypes.util

    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


def reuse_freed_images(mmap_threshold: int = 512 << 20, trim_threshold: int = 1 << 30) -> bool:
    """Let glibc's allocator keep freed large blocks for reuse (process-wide; False where it is not glibc).

    By default glibc maps every block above 32 MB afresh from the kernel and
    unmaps it on free, so each full-size work image of an arm (rectification
    maps of 3000 × 2000 px, 48 MB; the numpy matcher's 96 MB layouts when
    this was measured) is page-faulted in again: paper scale, arm A, 1.4 s
    of 15 s then. With blocks up to ``mmap_threshold`` bytes on the heap,
    and up to ``trim_threshold`` bytes of free heap kept, they are reused:
    about 1 s less per arm then, the process's peak memory 0.1-0.2 GB higher.

    It changes the whole process and cannot be undone (glibc has no getter
    for these settings), so library code never calls it for its caller: the
    command line's reconstruction commands and the benchmarks opt in at
    their entry point.
    """
    try:
        mallopt = _libc().mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(_M_TRIM_THRESHOLD,
                                                                                     int(trim_threshold)))


def return_freed_images() -> bool:
    """The opposite setting (process-wide, as :func:`reuse_freed_images`): blocks above 4 MB mapped afresh and
    given back to the system when freed, at most 32 MB of free heap kept.

    For a process that reconstructs several arms (``torsoscan reconstruct``):
    each arm's full-size images leave the resident set when the arm is done,
    instead of staying for the next one. Paper scale, seed 33, the arms two
    at a time on threads: the whole visit 0.86-0.94 GB at the peak
    (docs/benchmarks.md, the whole visit); with the allocator keeping freed
    blocks the four arms alone reached 1.56 GB, about 8 % faster (one run of
    an experiment, not a committed benchmark).
    """
    return reuse_freed_images(mmap_threshold=4 << 20, trim_threshold=32 << 20)


_PR_SET_PDEATHSIG = 1  # prctl option (linux/prctl.h)


def die_with_parent() -> bool:
    """Have the kernel end this process (SIGTERM) when the process that started it dies (Linux; False
    elsewhere).

    For the engine's own worker processes only (the simulator's renderers), called at their start: a killed
    ``torsoscan simulate`` would otherwise leave its spawned workers computing with no one to read their results
    (seen: render workers going on for minutes after their command was killed). The signal follows the thread that
    started the worker, so the pools that use it are created and shut down within one call."""
    import multiprocessing
    import signal

    # the process that started this one: a worker may start after its parent has already died
    started_by = multiprocessing.parent_process()
    parent = started_by.pid if started_by is not None else os.getppid()
    try:
        ok = _libc().prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
    if ok and os.getppid() != parent:  # the parent died before the call: nothing will signal us
        os.kill(os.getpid(), signal.SIGTERM)
    return ok


# read by OpenMP (Open3D's own, linked in: threadpoolctl cannot see it), OpenBLAS and MKL when they load, and by
# the engine's pools (cores)
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", THREADS_ENV)


def set_opencv_threads(n: int) -> int:
    """OpenCV's thread pool to ``n`` threads; returns what it was. Only where it differs: reconfiguring a pool
    a forked process inherited from a parent that had used it deadlocks (OpenCV 5, seen in a forked child)."""
    import cv2

    before = cv2.getNumThreads()
    if before != n:
        cv2.setNumThreads(n)
    return before


def limit_process_threads(n: int) -> None:
    """This process's thread pools to ``n`` threads, for good (process-wide): through the environment the
    libraries loaded from now on (OpenMP reads it once, when Open3D loads) and the engine's pools, OpenCV's pool,
    and BLAS and OpenMP already loaded (threadpoolctl, if installed). Only for processes whose owner shares the
    cores out among them: a Celery worker's pool processes, the simulator's render workers."""
    os.environ.update({k: str(n) for k in THREAD_ENV})
    set_opencv_threads(n)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: the environment still limits what loads from now on
        return
    threadpool_limits(limits=n)


def start_worker_process() -> None:
    """At the start of one of the engine's own worker processes, one per core (the simulator's renderers): end
    with the parent (:func:`die_with_parent`), and one thread for each library's pool (BLAS, OpenMP, OpenCV).

    The processes already use the cores; threads of the libraries' pools on
    top only wait on each other (OpenBLAS and OpenMP spin while they wait).
    Tiny preset, one test field's 60 images in 2 render processes on 2 cores:
    28 s of wall time and 52 s of CPU with the default pools, 18 s and 32 s
    with one thread each, the same images.
    """
    die_with_parent()
    limit_process_threads(1)
