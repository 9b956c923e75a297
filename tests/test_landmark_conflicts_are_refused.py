"""A landmark correction, click or undo posted from a page drawn before another change of the torso's landmarks
or frame is refused (409), saying what happened without blaming the wrong person.

The torsos are stand-ins (no analysis runs: the broker "takes" the landmark jobs and nothing runs them), so what
is tested is the view's check of ``based_on`` and what it tells the clinician.
"""

import re

import analysis.frame
import analysis.pictures
import pytest
from django.core.files.base import ContentFile
from django.core.files.storage import default_storage
from django.test import Client

from clinic import pipeline
from clinic.models import Job, Reconstruction
from tests.patient_records import two_torsos


@pytest.fixture
def torso(clinic, monkeypatch):
    """A visit's torso with a frame and a back picture (the pick form shows); landmark jobs queued, not run."""
    monkeypatch.setattr(pipeline, "send", lambda task, *args: True)
    _, (_, rec) = two_torsos(clinic, "RIG-Z", "P-Z", "Zoe Review")
    rec.indices = {"frame": {"drawn": 0}}
    rec.pictures = {"torso-back": default_storage.save("pictures/back-0.png", ContentFile(b"png 0"))}
    rec.save(update_fields=["indices", "pictures"])
    return rec


def _client(user):
    c = Client()
    c.force_login(user)
    return c


def _version(client, visit_id, form="landmarks") -> str:
    html = client.get(f"/visits/{visit_id}/").content.decode()
    m = re.search(rf'id="{form}">\s*<input type="hidden" name="csrfmiddlewaretoken" value="[^"]*">'
                  r'<input type="hidden" name="based_on" value="([^"]+)"', html)
    assert m, html[:2000]
    return m.group(1)


def _correct(client, visit_id, sp, based_on):
    return client.post(f"/visits/{visit_id}/landmarks", {"sacral_point": sp, "based_on": based_on})


@pytest.mark.django_db
def test_the_409_blames_no_one_who_changed_nothing_since_the_page_was_opened(charlie, ada, torso):
    """charlie corrects, ada corrects, charlie opens the page, ada undoes her correction: charlie's correction is
    refused, and the history's last entry (charlie's own, from before the page) is not named as the change."""
    v = torso.session.visit_id
    c, a = _client(charlie), _client(ada)
    assert _correct(c, v, "1 2 3", _version(c, v)).status_code == 302
    assert _correct(a, v, "4 5 6", _version(a, v)).status_code == 302
    seen = _version(c, v)
    assert a.post(f"/visits/{v}/landmarks/undo", {"based_on": _version(a, v)}).status_code == 302
    r = _correct(c, v, "7 8 9", seen)
    assert r.status_code == 409
    html = r.content.decode()
    assert "changed since this page was opened" in html and "(charlie at" not in html
    assert Reconstruction.objects.get(pk=torso.pk).landmarks == {"sacral_point": [1.0, 2.0, 3.0]}


@pytest.mark.django_db
def test_an_undo_from_a_page_drawn_before_another_undo_is_refused_as_a_conflict(charlie, ada, torso):
    """The undo posts a ``based_on`` that is not the torso's: a 409 like the other forms (nothing stored), not
    the 404 "no landmark correction to undo" the emptied history would give."""
    v = torso.session.visit_id
    c, a = _client(charlie), _client(ada)
    assert _correct(c, v, "1 2 3", _version(c, v)).status_code == 302
    seen = _version(a, v)  # ada's page shows "Undo the last correction"
    assert c.post(f"/visits/{v}/landmarks/undo", {"based_on": _version(c, v)}).status_code == 302
    r = a.post(f"/visits/{v}/landmarks/undo", {"based_on": seen})
    assert r.status_code == 409, r.status_code
    # with the page as it is now there is nothing to undo
    assert a.post(f"/visits/{v}/landmarks/undo", {"based_on": _version(a, v)}).status_code == 404


@pytest.mark.django_db
def test_a_click_on_a_picture_drawn_before_the_recompute_is_refused(charlie, torso,
                                                                                      monkeypatch):
    """A correction's job is queued; the visit page (its pick picture still the one drawn before, in the old
    frame) carries the torso's version. The job then stores new indices (a new frame) and pictures, which the
    covers: a click on the old picture is refused, not read through the new frame."""
    v = torso.session.visit_id
    c = _client(charlie)
    assert _correct(c, v, "1 2 3", _version(c, v)).status_code == 302
    assert Job.objects.get(kind=Job.LANDMARKS).state == Job.QUEUED
    seen = _version(c, v, form="pick")  # the page shows the picture drawn in frame 0

    # the worker finishes the correction's job as analyse_reconstruction does: new indices and pictures
    rec = Reconstruction.objects.get(pk=torso.pk)
    rec.indices = {"frame": {"drawn": 1}}
    rec.pictures = {"torso-back": default_storage.save("pictures/back-1.png", ContentFile(b"png 1"))}
    rec.save(update_fields=["indices", "pictures"])
    Job.objects.filter(kind=Job.LANDMARKS).update(state=Job.SUCCEEDED)

    frames = []
    monkeypatch.setattr(analysis.frame.PatientFrame, "from_dict", staticmethod(lambda d: d))
    monkeypatch.setattr(analysis.pictures, "pick_point",
                        lambda torso, frame, *a, **kw: frames.append(frame) or [10.0, 20.0, 30.0])
    r = c.post(f"/visits/{v}/landmarks/pick", {"landmark": "vertebra_prominens", "at.x": "400", "at.y": "300",
                                               "based_on": seen})
    assert r.status_code == 409, (r.status_code, "click read in frame", frames)
    assert Reconstruction.objects.get(pk=torso.pk).landmarks == {"sacral_point": [1.0, 2.0, 3.0]}
