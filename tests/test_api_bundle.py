"""The whole bundle as one zip: checked whole, stored whole, or refused with nothing kept."""

import io
import json
import zipfile

import pytest
from django.core.files.storage import default_storage

from clinic.models import CaptureSession
from tests.api_helpers import auth, small_bundle


def zip_folder(folder, extra=None):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(folder).as_posix())
        for name, data in (extra or {}).items():
            zf.writestr(name, data)
    return buf.getvalue()


def _post(client, key, data):
    return client.post("/api/bundles", data=data, content_type="application/zip", **auth(key))


def _stored_files(folder="captures"):
    """Every file under ``folder`` in the storage."""
    try:
        dirs, files = default_storage.listdir(folder)
    except FileNotFoundError:
        return []
    return [f"{folder}/{f}" for f in files] + [g for d in dirs for g in _stored_files(f"{folder}/{d}")]


@pytest.mark.django_db(transaction=True)
def test_a_zip_bundle_is_stored_and_finalized_once(client, small_rig, tmp_path):
    _, key = small_rig
    data = zip_folder(small_bundle(tmp_path))
    first, again = _post(client, key, data), _post(client, key, data)
    assert (first.status_code, again.status_code) == (201, 200)
    assert first.json()["id"] == again.json()["id"] and first.json()["state"] == "finalized"
    assert CaptureSession.objects.count() == 1


@pytest.mark.django_db(transaction=True)
def test_it_rejects_a_zip_with_a_path_outside_the_bundle(client, small_rig, tmp_path):
    _, key = small_rig
    before = _stored_files()
    r = _post(client, key, zip_folder(small_bundle(tmp_path), {"../../etc/evil.png": b"x"}))
    assert r.status_code == 400 and "../../etc/evil.png" in r.json()["detail"]
    assert CaptureSession.objects.count() == 0 and _stored_files() == before


@pytest.mark.django_db(transaction=True)
def test_a_bad_image_in_a_zip_keeps_nothing(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    manifest = json.loads((folder / "capture.json").read_text())
    manifest["images"][2]["sha256"] = "0" * 64
    (folder / "capture.json").write_text(json.dumps(manifest))
    r = _post(client, key, zip_folder(folder))
    assert r.status_code == 400 and "B1" in r.json()["detail"] and "sha256" in r.json()["detail"]
    assert CaptureSession.objects.count() == 0
    assert _stored_files() == []


@pytest.mark.django_db
def test_it_rejects_a_body_that_is_not_a_zip(client, small_rig):
    _, key = small_rig
    r = _post(client, key, b"not a zip")
    assert r.status_code == 400 and "not a zip" in r.json()["detail"]
