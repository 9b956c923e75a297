"""A raw upload body is bounded before it is read: a declared Content-Length above the limit is a 413 at once;
a chunked body is read to its end where the server delimits it (gunicorn), else refused with a 411, never read
as empty."""

import io
import json

import pytest

from clinic.models import CaptureImage, CaptureSession
from tests.api_helpers import auth, image_bytes, open_session, small_bundle
from tests.test_api_bundle import zip_folder


class Unreadable(io.RawIOBase):
    """A request body that must not be read."""

    def read(self, size=-1):
        raise AssertionError("the body was read")

    readline = read


def _raw(client, method, path, key, stream, **meta):
    """A request whose body is ``stream`` as the WSGI server hands it, with exactly the given META."""
    return client.generic(method, path, data=b"", content_type="application/octet-stream",
                          **{"wsgi.input": stream, **meta}, **auth(key))


@pytest.mark.django_db
def test_an_image_declared_larger_than_the_limit_is_refused_unread(client, small_rig, tmp_path, settings):
    _, key = small_rig
    sid = open_session(client, key, small_bundle(tmp_path)).json()["id"]
    r = _raw(client, "PUT", f"/api/sessions/{sid}/images/A1", key, Unreadable(),
             CONTENT_LENGTH=str(settings.MAX_IMAGE_BYTES + 1))
    assert r.status_code == 413 and "Content-Length" in r.json()["detail"] and "'A1'" in r.json()["detail"]


@pytest.mark.django_db
def test_a_bundle_declared_larger_than_the_limit_is_refused_unread(client, small_rig, settings):
    _, key = small_rig
    r = _raw(client, "POST", "/api/bundles", key, Unreadable(), CONTENT_LENGTH=str(settings.MAX_BUNDLE_BYTES + 1))
    assert r.status_code == 413 and "bundle" in r.json()["detail"]


@pytest.mark.django_db
def test_a_content_length_that_is_not_a_number_is_refused(client, small_rig):
    _, key = small_rig
    r = _raw(client, "POST", "/api/bundles", key, Unreadable(), CONTENT_LENGTH="lots")
    assert r.status_code == 400 and "'lots'" in r.json()["detail"]


@pytest.mark.django_db
def test_a_chunked_image_the_server_cannot_delimit_is_refused_not_read_as_empty(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    r = _raw(client, "PUT", f"/api/sessions/{sid}/images/A1", key, io.BytesIO(image_bytes(folder, "A1")),
             HTTP_TRANSFER_ENCODING="chunked")
    assert r.status_code == 411 and "Content-Length" in r.json()["detail"]
    assert not CaptureImage.objects.get(camera="A1").file


@pytest.mark.django_db
def test_a_chunked_image_is_read_to_its_end_where_the_server_delimits_it(client, small_rig, tmp_path):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    r = _raw(client, "PUT", f"/api/sessions/{sid}/images/A1", key, io.BytesIO(image_bytes(folder, "A1")),
             HTTP_TRANSFER_ENCODING="chunked", **{"wsgi.input_terminated": True})
    assert r.status_code == 201, r.content[:300]
    assert CaptureImage.objects.get(camera="A1").size == len(image_bytes(folder, "A1"))


@pytest.mark.django_db
def test_a_chunked_image_beyond_the_limit_is_cut_off(client, small_rig, tmp_path, settings):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    settings.MAX_IMAGE_BYTES = 64
    r = _raw(client, "PUT", f"/api/sessions/{sid}/images/A1", key, io.BytesIO(image_bytes(folder, "A1")),
             HTTP_TRANSFER_ENCODING="chunked", **{"wsgi.input_terminated": True})
    assert r.status_code == 413 and "64 bytes" in r.json()["detail"]
    assert not CaptureImage.objects.get(camera="A1").file


@pytest.mark.django_db(transaction=True)
def test_a_chunked_bundle_is_stored_where_the_server_delimits_it_and_refused_elsewhere(client, small_rig,
                                                                                        tmp_path):
    _, key = small_rig
    data = zip_folder(small_bundle(tmp_path))
    r = _raw(client, "POST", "/api/bundles", key, io.BytesIO(data), HTTP_TRANSFER_ENCODING="chunked")
    assert r.status_code == 411 and not CaptureSession.objects.exists()
    r = _raw(client, "POST", "/api/bundles", key, io.BytesIO(data), HTTP_TRANSFER_ENCODING="chunked",
             **{"wsgi.input_terminated": True})
    assert r.status_code == 201 and r.json()["state"] == "finalized", r.content[:300]


@pytest.mark.django_db
def test_a_json_body_beyond_djangos_limit_is_a_413(client, small_rig, settings):
    _, key = small_rig
    settings.DATA_UPLOAD_MAX_MEMORY_SIZE = 1000
    r = client.post("/api/sessions", data=json.dumps({"manifest": {"x": "y" * 2000}}),
                    content_type="application/json", **auth(key))
    assert r.status_code == 413 and "1000 bytes" in r.json()["detail"]
