"""While a landmark correction's indices are computed again (a job: on a worker, elsewhere than the request), the
visit page shows its progress and refreshes itself; a job whose worker died is taken over by the sweeper."""

from datetime import timedelta

import pytest
from django.utils import timezone

from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


def _latest(patient):
    from clinic.models import Reconstruction

    visit = patient.visits.order_by("-date").first()
    return visit, Reconstruction.objects.filter(session__visit=visit).get()


@pytest.mark.django_db
def test_the_visit_page_shows_the_recomputation_in_progress(client, charlie, patient_with_two_visits):  # noqa: F811
    from clinic.models import Job

    visit, rec = _latest(patient_with_two_visits)
    Job.objects.create(kind=Job.LANDMARKS, rig=rec.session.rig, session=rec.session, later=rec, state=Job.RUNNING,
                       stage="indices and pictures", percent=10, lease_until=timezone.now() + timedelta(seconds=60))
    client.force_login(charlie)
    page = client.get(f"/visits/{visit.pk}/").content.decode()
    assert "being computed again from the corrected landmarks: indices and pictures" in page
    assert '<progress max="100" value="10">' in page and 'http-equiv="refresh"' in page


@pytest.mark.django_db
def test_a_recomputation_whose_worker_died_is_done_again(patient_with_two_visits):  # noqa: F811
    from clinic import pipeline
    from clinic.models import Job

    visit, rec = _latest(patient_with_two_visits)
    before = dict(rec.pictures)
    job = Job.objects.create(kind=Job.LANDMARKS, rig=rec.session.rig, session=rec.session, later=rec,
                             state=Job.RUNNING, stage="indices and pictures", percent=10, attempt=1,
                             claimed=timezone.now() - timedelta(seconds=300),
                             lease_until=timezone.now() - timedelta(seconds=1),
                             dispatched=timezone.now() - timedelta(seconds=300))
    assert pipeline.redispatch_stalled(older_than=0) == [("clinic.tasks.run_landmark_analysis", job.pk)]
    job.refresh_from_db()
    assert (job.state, job.attempt) == (Job.SUCCEEDED, 2), job.error
    rec.refresh_from_db()
    assert set(rec.pictures) == set(before)
