"""Uploading image by image: hashes recomputed, repeats harmless, bad images refused, nothing half-stored."""

import json

import pytest
from django.core.files.storage import default_storage

from clinic.models import CaptureImage, CaptureSession
from tests.api_helpers import image_bytes, open_session, put, small_bundle


@pytest.mark.django_db
def test_retrying_the_session_request_never_makes_a_second_session(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    first = open_session(client, key, folder)
    again = open_session(client, key, folder)
    assert (first.status_code, again.status_code) == (201, 200)
    assert first.json()["id"] == again.json()["id"] and CaptureSession.objects.count() == 1


@pytest.mark.django_db
def test_an_idempotency_key_identifies_the_retry(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    manifest = json.loads((folder / "capture.json").read_text())
    ids = set()
    for _ in range(2):
        r = client.post("/api/sessions", data=json.dumps({"manifest": manifest}), content_type="application/json",
                        HTTP_AUTHORIZATION=f"Bearer {key}", HTTP_IDEMPOTENCY_KEY="rig-req-42")
        ids.add(r.json()["id"])
    assert len(ids) == 1


@pytest.mark.django_db
def test_it_rejects_an_unknown_camera(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path, cameras=("A1", "Z9"))
    r = open_session(client, key, folder)
    assert r.status_code == 400 and "Z9" in r.json()["detail"]
    sid = open_session(client, key, small_bundle(tmp_path, "ok", cameras=("A1", "A2"))).json()["id"]
    r = put(client, key, sid, "B1", image_bytes(folder, "A1"))
    assert r.status_code == 400 and "'B1'" in r.json()["detail"]


@pytest.mark.django_db
def test_it_rejects_a_checksum_mismatch_and_stores_nothing(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    r = put(client, key, sid, "A1", image_bytes(folder, "A2")[:-1] + b"\x00")
    assert r.status_code == 400 and "sha256 mismatch" in r.json()["detail"] and "A1" in r.json()["detail"]
    assert not CaptureImage.objects.get(camera="A1").file
    assert not default_storage.exists(f"captures/RIG-T/{sid}/images/A1.png")


@pytest.mark.django_db
def test_it_rejects_a_truncated_image(client, small_rig, tmp_path):
    from tests.boundary_fixtures import image
    import cv2

    _, key = small_rig
    cut = cv2.imencode(".png", image())[1].tobytes()[:-30]
    folder = small_bundle(tmp_path, images={"A1": cut})  # the manifest hashes the truncated bytes
    sid = open_session(client, key, folder).json()["id"]
    r = put(client, key, sid, "A1", cut)
    assert r.status_code == 400 and "truncated" in r.json()["detail"] and "A1" in r.json()["detail"]
    assert not CaptureImage.objects.get(camera="A1").file


@pytest.mark.django_db
def test_a_repeated_put_is_harmless_and_keeps_the_first(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    assert put(client, key, sid, "A1", image_bytes(folder, "A1")).status_code == 201
    stored = CaptureImage.objects.get(camera="A1").file.name
    r = put(client, key, sid, "A1", image_bytes(folder, "A1"))
    assert r.status_code == 200 and r.json()["stored"] == "already"
    assert CaptureImage.objects.get(camera="A1").file.name == stored
    assert default_storage.open(stored).read() == image_bytes(folder, "A1")
    # a different image under the same camera later is refused and the first stays
    r = put(client, key, sid, "A1", image_bytes(folder, "A2")[:-1] + b"\x00")
    assert r.status_code == 400
    assert default_storage.open(stored).read() == image_bytes(folder, "A1")


@pytest.mark.django_db
def test_it_rejects_an_image_of_the_wrong_size(client, small_rig, tmp_path):
    from tests.boundary_fixtures import image

    _, key = small_rig
    folder = small_bundle(tmp_path, images={"A1": image(shape=(20, 20))})
    sid = open_session(client, key, folder).json()["id"]
    r = put(client, key, sid, "A1", image_bytes(folder, "A1"))
    assert r.status_code == 400 and "20x20" in r.json()["detail"]
