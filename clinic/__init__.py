"""The clinic service: records, the rig's upload API, jobs, clinicians' pages."""

from .celery import app as celery_app

__all__ = ["celery_app"]
