"""A job's unexpected fault reads as words on the pages and the API; its traceback is in the server's log only.

The server's file paths and code lines are nobody's business on a clinician's page or a rig's API answer.
"""
import logging

import pytest

from clinic.models import Job
from tests.patient_records import two_torsos


@pytest.mark.django_db
def test_it_keeps_the_traceback_of_a_landmark_jobs_fault_off_the_visit_page(client, clinic, charlie, monkeypatch,
                                                                            caplog):
    import clinic.analysis_step as step

    _, (_, later) = two_torsos(clinic, "RIG-T", "P-7", "Pat Seven")

    def broken(rec):
        raise AttributeError("'NoneType' object has no attribute 'shape'")

    monkeypatch.setattr(step, "analyse_reconstruction", broken)
    client.force_login(charlie)
    visit = later.session.visit
    with caplog.at_level(logging.ERROR, logger="clinic.pipeline"):
        client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": "1 2 3"})
    job = Job.objects.get(kind=Job.LANDMARKS)
    assert job.state == Job.FAILED
    assert "AttributeError" in job.error and "File " not in job.error and ".py" not in job.error
    error_id = job.error.rsplit(" ", 1)[-1].rstrip(")")
    assert error_id in caplog.text and "Traceback" in caplog.text
    page = client.get(f"/visits/{visit.pk}/").content.decode()
    assert "The last landmark correction could not be applied" in page and "the correction is kept" in page
    assert "File &quot;" not in page and "pipeline.py" not in page
