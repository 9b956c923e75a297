"""Upload answers a rig can act on: a full disk is a 503 to retry, a reused Idempotency-Key for another capture
and a pose for a set that was already calibrated are refused before anything is stored."""

import errno
import json
import tempfile

import pytest

from clinic.models import CaptureSession, Job
from tests.api_helpers import auth, image_bytes, open_session, put, small_bundle
from tests.boundary_fixtures import image


class _FullTemp:
    """A temporary file on a full disk: writing fails as the kernel says (ENOSPC)."""

    def __init__(self, *a, **kw):
        self._f = tempfile.TemporaryFile()

    def write(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name):
        return getattr(self._f, name)


@pytest.mark.django_db
def test_a_full_upload_disk_asks_the_rig_to_retry(client, small_rig, tmp_path, monkeypatch):
    import clinic.api

    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    monkeypatch.setattr(clinic.api.tempfile, "NamedTemporaryFile", _FullTemp)
    r = put(client, key, sid, "A1", image_bytes(folder, "A1"))
    assert r.status_code == 503 and r.headers.get("Retry-After")
    assert "No space left on device" in r.json()["detail"]
    monkeypatch.undo()
    assert put(client, key, sid, "A1", image_bytes(folder, "A1")).status_code == 201  # the retry stores it


@pytest.mark.django_db
def test_it_refuses_another_capture_under_a_used_idempotency_key(client, small_rig, tmp_path):
    _, key = small_rig
    a = small_bundle(tmp_path, "a")
    b = small_bundle(tmp_path, "b", images={"A1": image(7)}, captured_at="2026-11-23T09:30:00+00:00")

    def post(folder):
        return client.post("/api/sessions", data=json.dumps({"manifest": json.loads((folder / "capture.json").read_text())}),
                           content_type="application/json", HTTP_IDEMPOTENCY_KEY="rig-counter-17", **auth(key))

    first = post(a)
    assert post(a).json()["id"] == first.json()["id"]  # a retry finds the first session
    r = post(b)
    assert r.status_code == 409 and "Idempotency-Key" in r.json()["detail"]
    assert CaptureSession.objects.count() == 1


@pytest.mark.django_db
def test_it_refuses_a_pose_for_a_set_already_calibrated(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path, "tf1", kind="testfield", images={"A1": image(101)})
    sid = open_session(client, key, folder, poses=1).json()["id"]
    for cam in ("A1", "A2", "B1"):
        assert put(client, key, sid, cam, image_bytes(folder, cam)).status_code == 201
    first = client.post(f"/api/sessions/{sid}/finalize", **auth(key)).json()
    assert [j["kind"] for j in first["jobs"]] == ["calibration"]
    again = small_bundle(tmp_path, "tf2", kind="testfield", images={"A1": image(102)})
    r = open_session(client, key, again, poses=1)
    assert r.status_code == 409 and first["calibration_set"] in r.json()["detail"]
    assert "new calibration_set" in r.json()["detail"]
    assert CaptureSession.objects.count() == 1 and Job.objects.count() == 1
