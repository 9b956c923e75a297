"""Small uploads that would inflate to gigabytes are refused before they inflate: an image's size is read from
its header and compared with its camera before decoding; a bundle's manifest and members are read bounded."""

import hashlib
import io
import json
import struct
import zipfile
import zlib

import cv2
import numpy as np
import pytest

from clinic.imageheaders import HeaderError, image_size
from clinic.models import CaptureImage, CaptureSession
from tests.api_helpers import auth, open_session, put, small_bundle
from tests.test_api_bundle import zip_folder


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_claiming(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width`` x ``height`` px, with one tiny IDAT (a decoder would allocate it all)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(b"\x00" * 1000))
            + _chunk(b"IEND", b""))


@pytest.mark.parametrize("ext", [".png", ".jpg", ".tif"])
def test_the_header_gives_the_size_of_every_capture_format(ext):
    data = cv2.imencode(ext, np.zeros((30, 40), np.uint8))[1].tobytes()
    assert image_size(io.BytesIO(data)) == (40, 30)


def test_the_header_of_anything_else_is_refused():
    with pytest.raises(HeaderError, match="not a PNG, JPEG or TIFF"):
        image_size(io.BytesIO(cv2.imencode(".bmp", np.zeros((30, 40), np.uint8))[1].tobytes()))
    with pytest.raises(HeaderError):
        image_size(io.BytesIO(png_claiming(40, 30)[:20]))


@pytest.mark.django_db
def test_an_image_claiming_20000_px_is_refused_before_decoding(client, small_rig, tmp_path, monkeypatch):
    import clinic.api

    def no_decoding(*a, **kw):
        raise AssertionError("the image was decoded")

    monkeypatch.setattr(clinic.api, "decode_image", no_decoding)
    _, key = small_rig
    bomb = png_claiming(20000, 20000)
    folder = small_bundle(tmp_path, images={"A1": bomb})
    sid = open_session(client, key, folder).json()["id"]
    r = put(client, key, sid, "A1", bomb)
    assert r.status_code == 400 and "20000x20000" in r.json()["detail"] and "'A1'" in r.json()["detail"]
    assert not CaptureImage.objects.get(camera="A1").file


@pytest.mark.django_db
def test_an_image_in_another_format_is_refused(client, small_rig, tmp_path):
    _, key = small_rig
    bmp = cv2.imencode(".bmp", np.zeros((30, 40), np.uint8))[1].tobytes()
    folder = small_bundle(tmp_path, images={"A1": bmp})
    sid = open_session(client, key, folder).json()["id"]
    r = put(client, key, sid, "A1", bmp)
    assert r.status_code == 400 and "not a PNG, JPEG or TIFF" in r.json()["detail"]


def _post(client, key, data):
    return client.post("/api/bundles", data=data, content_type="application/zip", **auth(key))


@pytest.mark.django_db
def test_a_50_mb_manifest_in_a_small_zip_is_refused_unread(client, small_rig, settings):
    _, key = small_rig
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("capture.json", b'{"rig": "' + b" " * (50 << 20) + b'"}')
    assert len(buf.getvalue()) < 200_000
    r = _post(client, key, buf.getvalue())
    assert r.status_code == 400 and "capture.json" in r.json()["detail"]
    assert str(settings.MAX_MANIFEST_BYTES) in r.json()["detail"]


@pytest.mark.django_db
def test_a_manifest_lying_about_its_size_is_refused_not_a_500(client, small_rig, settings, tmp_path):
    _, key = small_rig
    settings.MAX_MANIFEST_BYTES = 4096
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("capture.json", b" " * 100_000)
    data = bytearray(buf.getvalue())
    # the central directory's uncompressed size (offset 24 of its entry) claims 100 bytes
    cd = data.rfind(b"PK\x01\x02")
    data[cd + 24:cd + 28] = struct.pack("<I", 100)
    r = _post(client, key, bytes(data))
    assert r.status_code == 400 and "bundle.zip!capture.json" in r.json()["detail"]


@pytest.mark.django_db(transaction=True)
def test_a_zip_member_inflating_beyond_an_image_is_refused(client, small_rig, tmp_path, settings):
    _, key = small_rig
    settings.MAX_IMAGE_BYTES = 1 << 20
    zeros = b"\x00" * (5 << 20)
    folder = small_bundle(tmp_path)
    manifest = json.loads((folder / "capture.json").read_text())
    manifest["images"][0]["sha256"] = hashlib.sha256(zeros).hexdigest()
    (folder / "capture.json").write_text(json.dumps(manifest))
    (folder / "images" / "A1.png").write_bytes(zeros)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(folder).as_posix())
    r = _post(client, key, buf.getvalue())
    assert r.status_code == 400 and "images/A1.png" in r.json()["detail"] and "inflates" in r.json()["detail"]
    assert not CaptureSession.objects.exists()


@pytest.mark.django_db
def test_a_zip_of_thousands_of_members_is_refused_before_its_directory_is_parsed(client, small_rig, tmp_path):
    _, key = small_rig
    extra = {f"junk/{i}": b"" for i in range(1500)}
    r = _post(client, key, zip_folder(small_bundle(tmp_path), extra))
    assert r.status_code == 400 and "1504 members" in r.json()["detail"]


@pytest.mark.django_db
def test_a_manifest_nested_too_deeply_is_refused(client, small_rig):
    _, key = small_rig
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("capture.json", b"[" * 100_000 + b"]" * 100_000)
    r = _post(client, key, buf.getvalue())
    assert r.status_code == 400 and "capture.json" in r.json()["detail"]
