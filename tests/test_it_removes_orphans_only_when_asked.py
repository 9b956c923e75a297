"""--remove-orphans deletes the old unreferenced files, never a file a row names nor a young one (an upload in
flight stores its files before its row names them)."""

import pytest
from django.core.files.storage import default_storage

from tests.file_check_helpers import check_files, one_stored_image, stray_file


@pytest.mark.django_db
def test_it_removes_orphans_only_when_asked(client, small_rig, tmp_path):
    image = one_stored_image(client, small_rig[1], tmp_path)
    old = stray_file("results/gone-job/torso.ply", hours_old=3)
    young = stray_file("captures/RIG-T/incoming-4567/images/A2.png", hours_old=0.1)
    status, out = check_files("--remove-orphans")
    assert status == 0 and f"orphan {old} (removed)" in out and young not in out, out
    assert "1 orphaned (1 removed), 1 unreferenced but younger than the grace" in out
    assert not default_storage.exists(old)
    assert default_storage.exists(young) and default_storage.exists(image)
    status, out = check_files("--remove-orphans", "--grace-minutes", "0")
    assert status == 0 and f"orphan {young} (removed)" in out and default_storage.exists(image), out
