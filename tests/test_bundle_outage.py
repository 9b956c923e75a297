"""A bundle is never acknowledged broken: sent while the broker is down it is stored whole and its job runs once
the broker is back; a retry returns the same session, whole again if its files were lost; a failing store is a
503 the rig retries, never a 500."""

import hashlib
import json
import time

import pytest
from django.core.files.storage import default_storage

from clinic.models import CaptureImage, CaptureSession
from tests.api_helpers import auth, small_bundle
from tests.outage import clinic_with_own_broker, images_in_store
from tests.service_flow import calibrate_set, register_rig, wait_for_job
from tests.test_api_bundle import zip_folder


def test_it_keeps_a_bundle_sent_while_the_broker_was_down_and_runs_its_torso(tmp_path, rig_session_1):
    with clinic_with_own_broker(tmp_path) as (clinic, broker):
        clinic.start_worker()
        api = clinic.api
        key = register_rig(api, clinic.clinic_id, rig_session_1)
        assert calibrate_set(api, key, rig_session_1, "before")["state"] == "succeeded"
        folder = rig_session_1 / "captures" / "visit0-a"
        data = zip_folder(folder)

        broker.stop()
        path = f"/api/bundles?visit={clinic.visit_id}"
        first = api.call("POST", path, data=data, key=key, content_type="application/zip")
        assert first.status == 201, first.content[:500]
        again = api.call("POST", path, data=data, key=key, content_type="application/zip")  # the rig's retry
        assert again.status == 200, again.content[:500]
        session = first.json()
        assert again.json()["id"] == session["id"] and again.json()["jobs"] == session["jobs"]
        (job,) = session["jobs"]
        assert job["kind"] == "reconstruction" and job["state"] == "queued"
        stored = images_in_store(clinic, folder, session["id"])
        assert len(stored) == 20 and all(stored.values())

        broker.start()
        back = time.time()
        assert "1 step(s) re-dispatched" in clinic.sweep("--older-than", "0")
        done = wait_for_job(api, key, job["id"], timeout=300)
        assert done["state"] == "succeeded" and done["attempt"] == 1, done
        assert api.call("GET", f"/api/jobs/{job['id']}/files/torso.ply", key=key).status == 200
        print(f"the torso was done {time.time() - back:.1f} s after the broker came back")


def _bundle(client, key, data):
    return client.post("/api/bundles", data=data, content_type="application/zip", **auth(key))


@pytest.mark.django_db(transaction=True)
def test_it_stores_again_the_images_a_broken_session_lost(client, small_rig, tmp_path):
    # what the old defect left behind: a finalized session whose stored images were deleted
    _, key = small_rig
    folder = small_bundle(tmp_path)
    data = zip_folder(folder)
    first = _bundle(client, key, data)
    assert first.status_code == 201
    for image in CaptureImage.objects.all():
        default_storage.delete(image.file.name)

    again = _bundle(client, key, data)
    assert again.status_code == 200 and again.json()["id"] == first.json()["id"]
    assert CaptureSession.objects.count() == 1
    manifest = json.loads((folder / "capture.json").read_text())
    sha = {e["camera"]: e["sha256"] for e in manifest["images"]}
    for image in CaptureImage.objects.all():
        with default_storage.open(image.file.name, "rb") as fh:
            assert hashlib.sha256(fh.read()).hexdigest() == sha[image.camera]


@pytest.mark.django_db(transaction=True)
def test_it_answers_503_with_retry_after_when_the_store_fails(client, small_rig, tmp_path, settings):
    _, key = small_rig
    data = zip_folder(small_bundle(tmp_path))
    good = settings.STORAGES
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the store's folder should be")
    settings.STORAGES = {**good, "default": {"BACKEND": "django.core.files.storage.FileSystemStorage",
                                             "OPTIONS": {"location": str(blocker / "media")}}}
    r = _bundle(client, key, data)
    assert r.status_code == 503 and r["Retry-After"] == "30"
    assert "file store failed" in r.json()["detail"] and "retry" in r.json()["detail"]
    assert CaptureSession.objects.count() == 0

    settings.STORAGES = good  # the store is back: the retry completes the upload
    r = _bundle(client, key, data)
    assert r.status_code == 201 and r.json()["state"] == "finalized"
    assert all(default_storage.exists(im.file.name) for im in CaptureImage.objects.all())
