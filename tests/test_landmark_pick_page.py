"""On the visit page a clinician places a landmark by choosing it and clicking on the back picture: the skin point
drawn under the click becomes the landmark, and the indices are computed again (a job; in the embedded default it
runs within the request). A technician may not; another clinic's user gets 404; a click off the skin or without a
chosen landmark is refused, naming the field."""

import tempfile
from pathlib import Path

import numpy as np
import pytest

from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


def _latest(patient):
    from clinic.models import Reconstruction

    visit = patient.visits.order_by("-date").first()
    return visit, Reconstruction.objects.filter(session__visit=visit).get()


def _pixel_of(rec, point):
    """Where ``point`` (rig frame) is on the visit's back picture."""
    from analysis.frame import PatientFrame
    from analysis.pictures import render_view
    from clinic.analysis_step import local_copy

    with tempfile.TemporaryDirectory() as tmp:
        r = render_view(local_copy(rec.torso, Path(tmp) / "torso.ply"), PatientFrame.from_dict(rec.indices["frame"]),
                        "back")
    (x, y), = r.placement.project(np.asarray(point, float))[0]
    return x, y


@pytest.mark.django_db
def test_a_click_on_the_back_picture_places_the_chosen_landmark(client, charlie, patient_with_two_visits):  # noqa: F811
    visit, rec = _latest(patient_with_two_visits)
    client.force_login(charlie)
    page = client.get(f"/visits/{visit.pk}/").content.decode()
    assert 'id="pick"' in page and 'type="image" name="at"' in page
    automatic = np.asarray(rec.indices["landmarks"]["sacral_point"]["position_mm"], float)
    x, y = _pixel_of(rec, automatic + [0.0, 0.0, 20.0])  # 20 mm above the automatic sacral point
    r = client.post(f"/visits/{visit.pk}/landmarks/pick", {"landmark": "sacral_point", "at.x": f"{x:.0f}",
                                                           "at.y": f"{y:.0f}"})
    assert r.status_code == 302, r.content[:300]
    rec.refresh_from_db()
    placed = np.asarray(rec.landmarks["sacral_point"], float)
    assert abs(placed[2] - (automatic[2] + 20.0)) < 4.0 and np.hypot(*(placed - automatic)[:2]) < 15.0, placed
    assert rec.landmark_history[-1]["by"] == "charlie"
    # the indices were computed again from it (the job ran in the request here), and the page says nothing failed
    assert np.linalg.norm(np.subtract(rec.indices["landmarks"]["sacral_point"]["position_mm"], placed)) < 1.0
    assert "was undone" not in client.get(f"/visits/{visit.pk}/").content.decode()


@pytest.mark.django_db
def test_it_refuses_a_click_off_the_skin_or_without_a_landmark(client, charlie, patient_with_two_visits):  # noqa: F811
    visit, rec = _latest(patient_with_two_visits)
    client.force_login(charlie)
    r = client.post(f"/visits/{visit.pk}/landmarks/pick", {"landmark": "sacral_point", "at.x": "1", "at.y": "1"})
    assert r.status_code == 400 and b"no skin at (1, 1)" in r.content
    r = client.post(f"/visits/{visit.pk}/landmarks/pick", {"landmark": "navel", "at.x": "400", "at.y": "500"})
    assert r.status_code == 400 and b"landmark: choose one of" in r.content
    r = client.post(f"/visits/{visit.pk}/landmarks/pick", {"landmark": "sacral_point"})
    assert r.status_code == 400 and b"at: click on the back picture" in r.content
    rec.refresh_from_db()
    assert not rec.landmarks and not rec.landmark_history


@pytest.mark.django_db
def test_it_refuses_a_technician_and_hides_the_visit_from_another_clinic(client, alice, olga,
                                                                         patient_with_two_visits):  # noqa: F811
    visit, _ = _latest(patient_with_two_visits)
    client.force_login(alice)
    assert client.post(f"/visits/{visit.pk}/landmarks/pick", {"landmark": "sacral_point", "at.x": "400",
                                                              "at.y": "500"}).status_code == 403
    client.force_login(olga)
    assert client.post(f"/visits/{visit.pk}/landmarks/pick", {"landmark": "sacral_point", "at.x": "400",
                                                              "at.y": "500"}).status_code == 404
