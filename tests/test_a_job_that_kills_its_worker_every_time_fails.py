"""A step whose worker dies every time (a capture that runs it out of memory, say) is taken over
JOB_MAX_TAKEOVERS times, then its job fails saying why, instead of staying "running" for ever; a re-run starts
the count again. A long broker or worker outage is no takeover: a lapsed claim sent again and again before anyone
claims it counts once."""

from datetime import timedelta

import pytest
from django.test import override_settings
from django.utils import timezone

from clinic import pipeline
from clinic.models import Job
from tests.test_comparison_jobs import quick_analysis, two_scans  # noqa: F401 (fixtures)


class WorkerKilled(BaseException):
    """What the step's process sees of an OOM kill: nothing; the row stays as the claim left it."""


def _lapse(job):
    """The dead worker's lease runs out (its step was sent before it was claimed)."""
    now = timezone.now()
    Job.objects.filter(pk=job.pk).update(dispatched=now - timedelta(seconds=10), lease_until=now - timedelta(seconds=1))


@pytest.mark.django_db
@override_settings(JOB_MAX_TAKEOVERS=3)
def test_it_fails_a_job_whose_worker_dies_every_time(two_scans, quick_analysis, monkeypatch):  # noqa: F811
    import analysis.compare

    _, earlier, later = two_scans
    monkeypatch.setattr(pipeline, "send", lambda task, *args: True)  # a broker that takes every message

    def killed(*a, **kw):
        raise WorkerKilled()

    monkeypatch.setattr(analysis.compare, "compare_torsos", killed)
    job = pipeline.request_comparison(earlier, later)
    for death in range(4):
        with pytest.raises(WorkerKilled):
            pipeline.run_comparison(job.pk)
        _lapse(job)
        sent = pipeline.redispatch_stalled(older_than=0)
        if death < 3:
            assert sent == [("clinic.tasks.run_comparison", job.pk)]
            # nobody claims it (the broker or the workers are down): the same lapse is sent again, not counted again
            assert pipeline.redispatch_stalled(older_than=0) == [("clinic.tasks.run_comparison", job.pk)]
    job.refresh_from_db()
    assert sent == [] and job.state == Job.FAILED and job.takeovers == 3
    assert "stopped 4 times" in job.error and "re-run" in job.error
    job = pipeline.rerun(job)
    assert job.takeovers == 0 and job.state in (Job.QUEUED, Job.RUNNING, Job.FAILED)
