import copy

import pytest

from recon_engine.formats import FormatError, read_rig, write_rig
from tests.boundary_fixtures import RIG, write


def test_it_reads_and_writes_a_rig(tmp_path):
    rig = read_rig(write(tmp_path / "rig.json", RIG))
    assert rig.camera_ids == ["A1", "A2", "B1"] and rig.reference_arm.id == "A"
    assert rig.arm_of("B1").id == "B" and rig.cameras["A2"].width == 40
    write_rig(tmp_path / "again.json", rig)
    assert read_rig(tmp_path / "again.json") == rig


def _bad(tmp_path, change):
    obj = copy.deepcopy(RIG)
    change(obj)
    return write(tmp_path / "rig.json", obj)


def test_it_rejects_missing_format(tmp_path):
    with pytest.raises(FormatError, match=r"rig\.json: missing required key 'format'"):
        read_rig(_bad(tmp_path, lambda o: o.pop("format")))


def test_it_rejects_wrong_format(tmp_path):
    with pytest.raises(FormatError, match="format is 'torso-rig/2', expected 'torso-rig/1'"):
        read_rig(_bad(tmp_path, lambda o: o.update(format="torso-rig/2")))


def test_it_rejects_duplicate_camera(tmp_path):
    with pytest.raises(FormatError, match="duplicate camera 'A1'"):
        read_rig(_bad(tmp_path, lambda o: o["arms"][1]["cameras"].append("A1")))


def test_it_rejects_a_camera_without_entry(tmp_path):
    with pytest.raises(FormatError, match="camera 'B9'"):
        read_rig(_bad(tmp_path, lambda o: o["arms"][1]["cameras"].append("B9")))


def test_it_rejects_a_missing_camera_key_naming_camera_and_key(tmp_path):
    with pytest.raises(FormatError, match="missing required key 'pixel_size_mm' for camera 'A2'"):
        read_rig(_bad(tmp_path, lambda o: o["cameras"]["A2"].pop("pixel_size_mm")))


def test_it_rejects_a_bad_image_size(tmp_path):
    with pytest.raises(FormatError, match="camera 'A1' width must be positive"):
        read_rig(_bad(tmp_path, lambda o: o["cameras"]["A1"].update(width=0)))


def test_it_rejects_invalid_json_with_the_line(tmp_path):
    (tmp_path / "rig.json").write_text('{"format": "torso-rig/1",\n "serial": }')
    with pytest.raises(FormatError, match="invalid JSON at line 2"):
        read_rig(tmp_path / "rig.json")


def test_it_ignores_unknown_keys(tmp_path):
    rig = read_rig(_bad(tmp_path, lambda o: o.update(installed_by="someone")))
    assert rig.serial == "RIG-T"


def test_it_reads_and_writes_where_the_patients_back_faces(tmp_path):
    rig = read_rig(_bad(tmp_path, lambda o: o.update(patient={"back_towards": ["B", "A"]})))
    assert rig.back_towards == ("B", "A")
    write_rig(tmp_path / "again.json", rig)
    assert read_rig(tmp_path / "again.json") == rig


def test_it_rejects_a_patient_back_towards_an_unknown_arm(tmp_path):
    with pytest.raises(FormatError, match=r"patient\.back_towards names 'Z', which is no arm of the rig"):
        read_rig(_bad(tmp_path, lambda o: o.update(patient={"back_towards": ["Z"]})))
