"""check_files names a stored file that no row references, exits 1, and deletes nothing unasked."""

import pytest
from django.core.files.storage import default_storage

from tests.file_check_helpers import check_files, one_stored_image, stray_file


@pytest.mark.django_db
def test_it_reports_a_file_no_row_references(client, small_rig, tmp_path):
    image = one_stored_image(client, small_rig[1], tmp_path)
    assert check_files() == (0, "1 stored files, 1 named by rows: 0 orphaned (0 removed), 0 unreferenced but "
                                "younger than the grace, 0 rows' files missing\n")
    stray = stray_file("captures/RIG-T/incoming-0123/images/A1.png")
    status, out = check_files()
    assert status == 1 and f"orphan {stray}\n" in out and image not in out, out
    assert "1 orphaned (0 removed)" in out and "--remove-orphans" in out
    assert default_storage.exists(stray) and default_storage.exists(image)
