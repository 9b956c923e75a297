"""An uploaded image is flushed to the disk (file and folder entry) before the row naming it commits: after a power
cut no row names a truncated image, and a repeated upload's "already" is true."""

import os

import pytest
from django.core.files.storage import default_storage

from clinic.models import CaptureImage
from tests.api_helpers import image_bytes, open_session, put, small_bundle


@pytest.mark.django_db
def test_it_flushes_the_image_before_naming_it(client, small_rig, tmp_path, monkeypatch):
    _, key = small_rig
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    synced, real_fsync = [], os.fsync

    def fsync(fd):
        path = os.readlink(f"/proc/self/fd/{fd}")
        named = CaptureImage.objects.filter(session__uid=sid, camera="A1").exclude(file="").exists()
        synced.append((path, named))
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    assert put(client, key, sid, "A1", image_bytes(folder, "A1")).status_code == 201
    stored = default_storage.path(CaptureImage.objects.get(session__uid=sid, camera="A1").file.name)
    assert (stored, False) in synced  # the file, before its row named it
    assert (os.path.dirname(stored), False) in synced  # and its folder's entry
