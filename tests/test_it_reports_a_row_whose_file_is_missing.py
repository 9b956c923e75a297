"""check_files names a row whose stored file is gone (and which row), and exits 1; nothing is removed for it."""

import pytest
from django.core.files.storage import default_storage

from clinic.models import CaptureImage
from tests.file_check_helpers import check_files, one_stored_image


@pytest.mark.django_db
def test_it_reports_a_row_whose_file_is_missing(client, small_rig, tmp_path):
    image = one_stored_image(client, small_rig[1], tmp_path)
    default_storage.delete(image)
    status, out = check_files("--remove-orphans")
    row = CaptureImage.objects.get(camera="A1")
    assert status == 1 and f"missing {image} (named by clinic.CaptureImage {row.pk})" in out, out
    assert "1 rows' files missing" in out
    assert row.file.name == image  # the row is reported, not changed
