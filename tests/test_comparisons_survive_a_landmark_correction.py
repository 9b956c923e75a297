"""A landmark correction re-makes the comparisons resting on its torso, whatever happens meanwhile.

Its job removes them and records their new jobs in one commit (a worker killed after it loses none), and a
comparison that was running while the torso was corrected is not stored from the landmarks before (the
correction's job compares the pair again)."""

from datetime import timedelta

import pytest
from django.core.files.base import ContentFile
from django.utils import timezone

from clinic import pipeline
from clinic.models import Comparison, Job, Reconstruction
from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)
from tests.test_comparison_jobs import quick_analysis, two_scans  # noqa: F401 (fixtures)


class WorkerKilled(BaseException):
    """What the step's process sees of an OOM kill: nothing."""


@pytest.mark.django_db(transaction=True)
def test_a_worker_killed_after_the_comparisons_went_loses_none(patient_with_two_visits, monkeypatch):  # noqa: F811
    first, second = (Reconstruction.objects.get(session__visit=v) for v in patient_with_two_visits.visits.all())
    c = Comparison(earlier=first, later=second, report={"rms_mm": 1.0})
    c.deformation.save("deformation.ply", ContentFile(b"ply"), save=False)
    c.save()
    monkeypatch.setattr(pipeline, "send", lambda task, *args: True)
    job = Job.objects.create(kind=Job.LANDMARKS, rig_id=second.session.rig_id, session_id=second.session_id,
                             later=second)

    def killed(*a):
        raise WorkerKilled()

    monkeypatch.setattr(pipeline, "send_now", killed)  # dies right after its commit
    with pytest.raises(WorkerKilled):
        pipeline.run_landmark_analysis(job.pk)
    assert not Comparison.objects.filter(earlier=first, later=second).exists()
    redo = Job.objects.get(kind=Job.COMPARISON, earlier=first, later=second)
    assert redo.state == Job.QUEUED
    Job.objects.filter(pk=redo.pk).update(dispatched=timezone.now() - timedelta(hours=1))
    assert ("clinic.tasks.run_comparison", redo.pk) in pipeline.redispatch_stalled()


@pytest.mark.django_db
def test_a_comparison_finished_after_a_correction_is_not_stored(two_scans, quick_analysis, monkeypatch):  # noqa: F811
    import analysis.compare

    from clinic import analysis_step

    _, earlier, later = two_scans
    monkeypatch.setattr(pipeline, "send", lambda task, *args: True)
    monkeypatch.setattr(analysis_step, "analyse_reconstruction", lambda rec: rec)  # quick stand-in
    stand_in = analysis.compare.compare_torsos
    calls = []

    def compare_while_corrected(e, l, **kw):
        calls.append(kw.get("later_landmarks"))
        if len(calls) == 1:  # a clinician corrects the later torso meanwhile; its landmark job runs elsewhere
            Reconstruction.objects.filter(pk=later.pk).update(landmarks={"sacral_point": [9.0, 9.0, 9.0]})
            lj = Job.objects.create(kind=Job.LANDMARKS, rig_id=later.session.rig_id, session_id=later.session_id,
                                    later=later)
            assert pipeline.run_landmark_analysis(lj.pk) == "succeeded"
        return stand_in(e, l, **kw)

    monkeypatch.setattr(analysis.compare, "compare_torsos", compare_while_corrected)
    job = pipeline.request_comparison(earlier, later)
    assert pipeline.run_comparison(job.pk) == "stale"
    assert not Comparison.objects.filter(earlier=earlier, later=later).exists()
    redo = Job.objects.get(kind=Job.COMPARISON, earlier=earlier, later=later)  # the correction's, queued
    assert redo.pk != job.pk and redo.state == Job.QUEUED
    assert pipeline.run_comparison(redo.pk) == "succeeded"
    assert calls[-1] == {"sacral_point": [9.0, 9.0, 9.0]}
