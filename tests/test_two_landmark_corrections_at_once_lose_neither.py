"""Two clinicians correcting the same torso: neither correction is silently lost.

A correction is applied to the landmarks stored when it commits (the torso's row is locked and read again), and
one posted from a page drawn before someone else's correction or undo is refused (409) without storing anything.
"""

import re

import analysis.pictures
import pytest

from clinic import views
from clinic.models import Job, Reconstruction
from tests.test_browser_comparison import patient_with_two_visits  # noqa: F401 (fixture)


def _version(client, visit) -> str:
    html = client.get(f"/visits/{visit.pk}/").content.decode()
    versions = set(re.findall(r'name="based_on" value="([^"]+)"', html))
    assert len(versions) == 1, versions  # every landmark form of the page carries the same
    return versions.pop()


def _xyz(p):
    return " ".join(f"{c:.1f}" for c in p)


@pytest.mark.django_db
def test_it_refuses_a_correction_from_a_page_drawn_before_another(client, charlie, patient_with_two_visits):  # noqa: F811
    visit = patient_with_two_visits.visits.first()
    rec = Reconstruction.objects.get(session__visit=visit)
    auto = rec.indices["landmarks"]["sacral_point"]["position_mm"]
    client.force_login(charlie)
    seen = _version(client, visit)  # two clinicians open the visit page
    first = [round(c, 1) for c in (auto[0] + 5.0, auto[1], auto[2] + 20.0)]
    r = client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": _xyz(first), "based_on": seen})
    assert r.status_code == 302
    jobs = Job.objects.filter(kind=Job.LANDMARKS).count()

    # the second posts from the page drawn before the first correction
    late = [round(c, 1) for c in (auto[0] - 5.0, auto[1], auto[2] - 20.0)]
    r = client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": _xyz(late), "based_on": seen})
    assert r.status_code == 409
    html = r.content.decode()
    assert "landmarks changed since this page was opened" in html and "nothing was stored" in html
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": first} and len(rec.landmark_history) == 1
    assert Job.objects.filter(kind=Job.LANDMARKS).count() == jobs
    # an undo from that stale page would undo the other's correction: refused too
    assert client.post(f"/visits/{visit.pk}/landmarks/undo", {"based_on": seen}).status_code == 409
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": first}

    # from the page as it is now, both go through
    r = client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": _xyz(late), "based_on": _version(client, visit)})
    assert r.status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": late}
    assert client.post(f"/visits/{visit.pk}/landmarks/undo", {"based_on": _version(client, visit)}).status_code == 302
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": first}


@pytest.mark.django_db
def test_a_landmark_placed_while_another_was_stored_keeps_both(client, charlie, patient_with_two_visits,  # noqa: F811
                                                               monkeypatch):
    """The request read the torso before another request's correction committed (as two requests at once do):
    the correction is made on what is stored, not on the request's own copy."""
    visit = patient_with_two_visits.visits.first()
    rec = Reconstruction.objects.get(session__visit=visit)
    stale = Reconstruction.objects.get(pk=rec.pk)  # read before the other correction
    sacral = [round(c, 1) for c in rec.indices["landmarks"]["sacral_point"]["position_mm"]]
    vp = [round(c, 1) for c in rec.indices["landmarks"]["vertebra_prominens"]["position_mm"]]
    client.force_login(charlie)
    assert client.post(f"/visits/{visit.pk}/landmarks", {"sacral_point": _xyz(sacral)}).status_code == 302

    monkeypatch.setattr(views, "best_scan", lambda v: stale)
    monkeypatch.setattr(analysis.pictures, "pick_point", lambda *a, **kw: vp)  # the click lands on the VP
    r = client.post(f"/visits/{visit.pk}/landmarks/pick", {"landmark": "vertebra_prominens", "at.x": "400",
                                                            "at.y": "300"})
    assert r.status_code == 302, r.content.decode()[:300]
    rec.refresh_from_db()
    assert rec.landmarks == {"sacral_point": sacral, "vertebra_prominens": vp}
    assert [h["landmarks"] for h in rec.landmark_history] == [None, {"sacral_point": sacral}]
