"""Celery tasks: thin wrappers that carry job ids; the work and its state live in ``pipeline``.

Every task is acknowledged late and rejected when its worker is lost (see
settings), so a crash re-delivers it; the conditional claims in ``pipeline``
make the second delivery harmless (and let it take over a claim whose lease
lapsed). Only transient faults (the database or the broker unreachable) are
retried, a bounded number of times. The next step is sent with
``pipeline.send``: if the broker is down, the rows keep it and the sweeper
(``redispatch_stalled``, on the beat) sends it later.
"""

from celery import shared_task

from . import pipeline
from .celery import task_thread_limits

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
    # separate tasks, not a chord: the arms join through the job's row (pipeline.reconstruct_arm)
    sent = sum(pipeline.send(reconstruct_arm, job_id, arm) for arm in arms)
    return f"{sent} of {len(arms)} arms dispatched"


@shared_task(**RETRY)
def reconstruct_arm(job_id: int, arm: str) -> str:
    # several arm tasks run side by side in a worker: each keeps to its share of the cores (see clinic.celery)
    with task_thread_limits():
        outcome = pipeline.reconstruct_arm(job_id, arm)
    if outcome == "arms done":
        pipeline.send(register, job_id)
    return outcome


@shared_task(**RETRY)
def register(job_id: int) -> str:
    return pipeline.register(job_id)


@shared_task(**RETRY)
def run_comparison(job_id: int) -> str:
    """Two torsos compared, asked for on the comparison page (the page shows its progress)."""
    return pipeline.run_comparison(job_id)


@shared_task(**RETRY)
def run_landmark_analysis(job_id: int) -> str:
    """A torso's indices and pictures from its corrected landmarks (the visit page shows the progress)."""
    return pipeline.run_landmark_analysis(job_id)


@shared_task(**RETRY)
def flag_rigs_for_recalibration() -> list:
    """Scheduled (Celery beat): rigs due for recalibration are flagged."""
    return pipeline.flag_rigs_for_recalibration()


@shared_task
def redispatch_stalled() -> list:
    """Scheduled (Celery beat): queued work the broker never got or lost, and steps whose worker died, are sent
    again. Not retried: the next beat is the retry."""
    return pipeline.redispatch_stalled()


@shared_task
def check_files() -> str:
    """Scheduled (Celery beat): stored files no row references and rows whose file is missing are logged (removal
    is left to ``manage.py check_files --remove-orphans``, run by a person)."""
    from . import filecheck

    return filecheck.check().summary()
