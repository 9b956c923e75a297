"""An installation with one stored image a row names, for the stored-files check's tests."""

import os
import time

from django.core.files.base import ContentFile
from django.core.files.storage import default_storage
from django.core.management import call_command

from clinic.models import CaptureImage
from tests.api_helpers import image_bytes, open_session, put, small_bundle


def one_stored_image(client, key, tmp_path) -> str:
    """The storage name of an image uploaded through the API (a row names it)."""
    folder = small_bundle(tmp_path)
    sid = open_session(client, key, folder).json()["id"]
    assert put(client, key, sid, "A1", image_bytes(folder, "A1")).status_code == 201
    return CaptureImage.objects.get(camera="A1").file.name


def stray_file(name: str, hours_old: float = 2) -> str:
    """A stored file no row names, last modified ``hours_old`` ago."""
    name = default_storage.save(name, ContentFile(b"left behind by a failed upload"))
    then = time.time() - hours_old * 3600
    os.utime(default_storage.path(name), (then, then))
    return name


def check_files(*args):
    """(exit status, output) of ``manage.py check_files``."""
    from io import StringIO

    from django.core.management.base import CommandError

    out = StringIO()
    try:
        call_command("check_files", *args, stdout=out)
        return 0, out.getvalue()
    except CommandError as exc:
        return 1, out.getvalue() + str(exc)
