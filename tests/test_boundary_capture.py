import hashlib
import json
import os
import stat
import zipfile

import cv2
import numpy as np
import pytest

from recon_engine.formats import (FormatError, load_image, load_images, missing_cameras, read_capture,
                                  read_rig, write_capture, zip_capture)
from tests.boundary_fixtures import RIG, bundle, image, write


@pytest.fixture
def rig(tmp_path):
    return read_rig(write(tmp_path / "rig.json", RIG))


def _manifest(folder):
    return json.loads((folder / "capture.json").read_text())


def _rewrite(folder, change):
    m = _manifest(folder)
    change(m)
    write(folder / "capture.json", m)


def test_it_reads_zip_and_folder_alike(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    z = zip_capture(folder, tmp_path / "cap.zip")
    a, b = read_capture(folder, rig), read_capture(z, rig)
    assert a.cameras == b.cameras == ["A1", "A2", "B1"]
    for cam in a.cameras:
        assert np.array_equal(load_image(a, cam, rig), load_image(b, cam, rig))


def test_it_reads_a_zip_whose_bundle_sits_in_one_folder(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    with zipfile.ZipFile(tmp_path / "nested.zip", "w") as zf:
        for f in folder.rglob("*"):
            if f.is_file():
                zf.write(f, "cap/" + f.relative_to(folder).as_posix())
    assert read_capture(tmp_path / "nested.zip", rig).cameras == ["A1", "A2", "B1"]


def test_it_rejects_unknown_camera(tmp_path, rig):
    folder = bundle(tmp_path / "cap", cameras=("A1", "Z9"))
    with pytest.raises(FormatError, match="capture.json: unknown camera 'Z9'"):
        read_capture(folder, rig)


def test_it_rejects_duplicate_camera(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    _rewrite(folder, lambda m: m["images"].append(dict(m["images"][0])))
    with pytest.raises(FormatError, match="duplicate camera 'A1'"):
        read_capture(folder, rig)


def test_it_rejects_missing_format(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    _rewrite(folder, lambda m: m.pop("format"))
    with pytest.raises(FormatError, match="capture.json: missing required key 'format'"):
        read_capture(folder, rig)


def test_it_rejects_wrong_format(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    _rewrite(folder, lambda m: m.update(format="torso-capture/9"))
    with pytest.raises(FormatError, match="format is 'torso-capture/9'"):
        read_capture(folder, rig)


def test_it_rejects_a_testfield_capture_without_pose(tmp_path, rig):
    folder = bundle(tmp_path / "cap", kind="testfield")
    _rewrite(folder, lambda m: m.pop("pose"))
    with pytest.raises(FormatError, match="missing required key 'pose'"):
        read_capture(folder, rig)


def test_it_rejects_another_rig(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    _rewrite(folder, lambda m: m.update(rig="RIG-OTHER"))
    with pytest.raises(FormatError, match="rig is 'RIG-OTHER'"):
        read_capture(folder, rig)


def test_it_rejects_image_size_different_from_rig(tmp_path, rig):
    folder = bundle(tmp_path / "cap", images={"A2": image(shape=(31, 40))})
    cap = read_capture(folder, rig)
    with pytest.raises(FormatError, match=r"A2\.png: camera 'A2': image is 40x31 px, rig.json says 40x30"):
        load_image(cap, "A2", rig)


def test_it_rejects_sha256_mismatch(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    _rewrite(folder, lambda m: m["images"][1].update(sha256="0" * 64))
    with pytest.raises(FormatError, match=r"A2\.png: camera 'A2': sha256 mismatch \(manifest 0000"):
        load_image(read_capture(folder, rig), "A2", rig)


def test_it_rejects_a_malformed_sha256(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    _rewrite(folder, lambda m: m["images"][0].update(sha256="abc"))
    with pytest.raises(FormatError, match="camera 'A1': sha256 must be 64 hex digits"):
        read_capture(folder, rig)


def test_it_rejects_truncated_image(tmp_path, rig):
    data = cv2.imencode(".png", image())[1].tobytes()
    folder = bundle(tmp_path / "cap", images={"B1": data[: len(data) // 2]})
    with pytest.raises(FormatError, match=r"B1\.png: camera 'B1': image is truncated"):
        load_image(read_capture(folder, rig), "B1", rig)


def test_it_rejects_unreadable_image(tmp_path, rig):
    folder = bundle(tmp_path / "cap", images={"B1": b"not an image at all" + b"IEND\xaeB`\x82"})
    with pytest.raises(FormatError, match="camera 'B1': cannot decode the image"):
        load_image(read_capture(folder, rig), "B1", rig)


def test_it_rejects_unsupported_bit_depth(tmp_path, rig):
    data = cv2.imencode(".tiff", np.zeros((30, 40), np.float32))[1].tobytes()
    folder = bundle(tmp_path / "cap", cameras=("A1",))
    (folder / "images" / "A1.tiff").write_bytes(data)
    _rewrite(folder, lambda m: m["images"][0].update(file="images/A1.tiff", sha256=hashlib.sha256(data).hexdigest()))
    with pytest.raises(FormatError, match="camera 'A1': unsupported bit depth"):
        load_image(read_capture(folder, rig), "A1", rig)


def test_it_accepts_16_bit_and_colour_images(tmp_path, rig):
    colour = np.dstack([image()] * 3)
    folder = bundle(tmp_path / "cap", images={"A1": image(4000, dtype=np.uint16), "A2": colour})
    imgs = load_images(read_capture(folder, rig), rig)
    assert imgs["A1"].dtype == np.uint16 and imgs["A1"].shape == (30, 40)
    assert imgs["A2"].ndim == 2


def test_it_rejects_missing_image_file(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    os.remove(folder / "images" / "A2.png")
    with pytest.raises(FormatError, match=r"A2\.png: camera 'A2': image file is missing"):
        read_capture(folder, rig)


def test_it_rejects_an_image_path_outside_the_bundle(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    _rewrite(folder, lambda m: m["images"][0].update(file="../secret.png"))
    with pytest.raises(FormatError, match="file '../secret.png' lies outside the bundle"):
        read_capture(folder, rig)


def test_it_rejects_zip_member_outside_bundle(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    z = zip_capture(folder, tmp_path / "cap.zip")
    with zipfile.ZipFile(z, "a") as zf:
        zf.writestr("../evil.png", b"x")
    with pytest.raises(FormatError, match=r"cap\.zip: zip member '../evil.png' lies outside the bundle"):
        read_capture(z, rig)


def test_it_rejects_zip_symlink_member(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    z = zip_capture(folder, tmp_path / "cap.zip")
    with zipfile.ZipFile(z, "a") as zf:
        info = zipfile.ZipInfo("images/link.png")
        info.external_attr = (stat.S_IFLNK | 0o777) << 16
        zf.writestr(info, "/etc/passwd")
    with pytest.raises(FormatError, match="zip member 'images/link.png' is a symbolic link"):
        read_capture(z, rig)


def test_it_rejects_a_zip_missing_an_image(tmp_path, rig):
    folder = bundle(tmp_path / "cap")
    with zipfile.ZipFile(tmp_path / "cap.zip", "w") as zf:
        zf.write(folder / "capture.json", "capture.json")
        zf.write(folder / "images" / "A1.png", "images/A1.png")
    with pytest.raises(FormatError, match=r"cap\.zip!images/A2\.png: camera 'A2': image file is missing"):
        read_capture(tmp_path / "cap.zip", rig)


def test_a_missing_camera_is_reported_not_refused(tmp_path, rig):
    cap = read_capture(bundle(tmp_path / "cap", cameras=("A1", "B1")), rig)
    assert missing_cameras(cap, rig) == ["A2"]


def test_write_capture_round_trips_and_refuses_to_overwrite(tmp_path, rig):
    imgs = {"A1": image(10), "B1": image(200)}
    cap = write_capture(tmp_path / "out", kind="testfield", rig="RIG-T", captured_at="2026-11-22T08:00:00+00:00",
                        images=imgs, testfield="tower", pose=2, extra={"roi": {"A1": [[0, 0], [5, 0], [5, 5]]}})
    again = read_capture(tmp_path / "out", rig)
    assert again.pose == 2 and again.testfield == "tower" and again.extra["roi"]["A1"][1] == [5, 0]
    assert np.array_equal(load_image(again, "B1", rig), imgs["B1"])
    with pytest.raises(FileExistsError):
        write_capture(tmp_path / "out", kind="torso", rig="RIG-T", captured_at="x", images=imgs)
    assert cap.cameras == ["A1", "B1"]
