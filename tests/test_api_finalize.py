"""Finalizing a session: complete, partial with the missing cameras named, never twice."""

import pytest

from clinic.models import Job
from tests.api_helpers import auth, image_bytes, open_session, put, small_bundle


def _upload(client, key, folder, cameras):
    sid = open_session(client, key, folder).json()["id"]
    for cam in cameras:
        assert put(client, key, sid, cam, image_bytes(folder, cam)).status_code == 201
    return sid


@pytest.mark.django_db(transaction=True)
def test_an_incomplete_session_is_not_finalized_unless_partial(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = _upload(client, key, folder, ["A1", "A2"])
    r = client.post(f"/api/sessions/{sid}/finalize", **auth(key))
    assert r.status_code == 409 and "B1" in r.json()["detail"]
    r = client.post(f"/api/sessions/{sid}/finalize?partial=true", **auth(key))
    assert r.status_code == 200
    body = r.json()
    assert body["state"] == "partial" and body["missing"] == ["B1"]
    # a torso session starts its reconstruction job (failed here: the rig has no calibration yet)
    job = Job.objects.get(session__uid=sid)
    assert job.kind == "reconstruction" and job.state == "failed" and "no calibration" in job.error


@pytest.mark.django_db(transaction=True)
def test_it_rejects_a_session_finalized_twice(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = _upload(client, key, folder, ["A1", "A2", "B1"])
    assert client.post(f"/api/sessions/{sid}/finalize", **auth(key)).status_code == 200
    r = client.post(f"/api/sessions/{sid}/finalize", **auth(key))
    assert r.status_code == 409 and "already finalized" in r.json()["detail"]
    assert Job.objects.filter(session__uid=sid).count() == 1
    r = put(client, key, sid, "A1", image_bytes(folder, "A1"))
    assert r.status_code == 409
