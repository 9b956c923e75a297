"""A landmark correction can be undone, and the comparisons resting on the corrected torso are computed again."""

import pytest
from django.core.files.base import ContentFile
from django.core.files.storage import default_storage

from tests.patient_records import correct_sacral_point
from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


@pytest.mark.django_db
def test_it_undoes_the_last_correction_and_says_who_made_it(client, charlie, patient_with_two_visits):  # noqa: F811
    visit = patient_with_two_visits.visits.first()
    rec, auto, moved, r = correct_sacral_point(client, charlie, visit)
    assert r.status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": moved}
    assert [h["landmarks"] for h in rec.landmark_history] == [None] and rec.landmark_history[0]["by"] == "charlie"
    page = client.get(f"/visits/{visit.pk}/").content.decode()
    assert "Undo the last correction" in page and "made by charlie" in page

    assert client.post(f"/visits/{visit.pk}/landmarks/undo").status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks is None and rec.landmark_history == []
    assert rec.indices["landmarks"]["sacral_point"]["position_mm"] == pytest.approx(auto, abs=0.01)
    # nothing left to undo
    assert client.post(f"/visits/{visit.pk}/landmarks/undo").status_code == 404


@pytest.mark.django_db
def test_it_refuses_an_undo_from_a_user_of_another_clinic(client, olga, patient_with_two_visits):  # noqa: F811
    visit = patient_with_two_visits.visits.first()
    client.force_login(olga)
    assert client.post(f"/visits/{visit.pk}/landmarks/undo").status_code == 404


@pytest.mark.django_db(transaction=True)
def test_a_corrected_torso_loses_its_stale_comparisons_and_their_files(patient_with_two_visits):  # noqa: F811
    from django.db import transaction

    from clinic import pipeline
    from clinic.models import Comparison, Job, Reconstruction

    first, second = (Reconstruction.objects.get(session__visit=v) for v in patient_with_two_visits.visits.all())
    c = Comparison(earlier=first, later=second, report={"rms_mm": 1.0})
    c.deformation.save("deformation.ply", ContentFile(b"ply"), save=False)
    c.save()
    Job.objects.create(kind=Job.COMPARISON, rig_id=second.session.rig_id, session=second.session, earlier=first,
                       later=second, state=Job.SUCCEEDED)
    stored = c.deformation.name
    with transaction.atomic():
        pairs = pipeline.forget_comparisons_of(first)
        assert default_storage.exists(stored)  # not before the commit: a rollback keeps the comparison whole
    assert [(e.pk, la.pk) for e, la in pairs] == [(first.pk, second.pk)]
    assert not Comparison.objects.exists() and not Job.objects.filter(kind=Job.COMPARISON).exists()
    assert not default_storage.exists(stored)
