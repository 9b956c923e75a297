"""The comparison page reads the comparison, then its job: a job that finishes in between (it stores the
comparison, then marks itself succeeded) shows its result, not "These two scans have not been compared yet"
(the self-refreshing page stopped there)."""

import pytest

from clinic import pipeline, tasks
from clinic.models import Comparison
from tests.test_comparison_jobs import quick_analysis, two_scans  # noqa: F401 (fixtures)


def _url(patient, earlier, later):
    return f"/patients/{patient.pk}/compare/?earlier_scan={earlier.pk}&later_scan={later.pk}"


@pytest.mark.django_db
def test_a_job_finishing_during_the_pages_read_shows_its_result(client, charlie, two_scans,  # noqa: F811
                                                                                    quick_analysis,  # noqa: F811
                                                                                    monkeypatch):
    patient, earlier, later = two_scans
    monkeypatch.setattr(pipeline, "send", lambda task, *args: True)  # a worker will take it
    job = pipeline.request_comparison(earlier, later)
    client.force_login(charlie)
    assert 'http-equiv="refresh"' in client.get(_url(patient, earlier, later)).content.decode()

    job_of = pipeline.comparison_job_of

    def the_worker_finishes_meanwhile(*args):  # between the page's two reads
        assert tasks.run_comparison.delay(job.pk).get() == "succeeded"
        return job_of(*args)

    monkeypatch.setattr(pipeline, "comparison_job_of", the_worker_finishes_meanwhile)
    html = client.get(_url(patient, earlier, later)).content.decode()
    assert Comparison.objects.filter(earlier=earlier, later=later).exists()
    assert 'id="deformation"' in html, "stuck on: not compared yet"
