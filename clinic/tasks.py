"""Celery tasks: thin wrappers that carry job ids; the work and its state live in ``pipeline``.

Every task is acknowledged late and rejected when its worker is lost (see
settings), so a crash re-delivers it; the conditional claims in ``pipeline``
make the second delivery harmless. Only transient faults (the database or
the broker unreachable) are retried, a bounded number of times.
"""

from celery import group, shared_task

from . import pipeline

RETRY = dict(autoretry_for=pipeline.TRANSIENT, retry_backoff=5, retry_backoff_max=120, retry_jitter=True,
             max_retries=3)


@shared_task
def ping() -> str:
    """Proves the wiring between the web app, the broker and a worker."""
    return "pong"


@shared_task(**RETRY)
def run_calibration(job_id: int) -> str:
    return pipeline.run_calibration(job_id)


@shared_task(**RETRY)
def start_reconstruction(job_id: int) -> str:
    arms = pipeline.start_reconstruction(job_id)
    if arms:
        # a group, not a chord: the arms join through the job's row (pipeline.reconstruct_arm)
        group(reconstruct_arm.s(job_id, arm) for arm in arms).apply_async()
    return f"{len(arms)} arms dispatched"


@shared_task(**RETRY)
def reconstruct_arm(job_id: int, arm: str) -> str:
    outcome = pipeline.reconstruct_arm(job_id, arm)
    if outcome == "arms done":
        register.delay(job_id)
    return outcome


@shared_task(**RETRY)
def register(job_id: int) -> str:
    return pipeline.register(job_id)


@shared_task(**RETRY)
def flag_rigs_for_recalibration() -> list:
    """Scheduled (Celery beat): rigs due for recalibration are flagged."""
    return pipeline.flag_rigs_for_recalibration()
