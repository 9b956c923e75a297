"""Celery tasks. Later issues add the reconstruction and calibration jobs."""

from celery import shared_task


@shared_task
def ping() -> str:
    """Proves the wiring between the web app, the broker and a worker."""
    return "pong"
