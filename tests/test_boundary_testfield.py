import pytest

from recon_engine.formats import FormatError, TestField, read_testfield, write_testfield
from tests.boundary_fixtures import write

GOOD = {"format": "torso-testfield/1", "name": "tower", "aruco_dictionary": "DICT_4X4_1000",
        "markers": {"17": [[0, 0, 0], [70, 0, 0], [70, 0, -70], [0, 0, -70]]}, "sigma_mm": 0.05}


def test_it_round_trips(tmp_path):
    tf = read_testfield(write(tmp_path / "tf.json", GOOD))
    assert tf.name == "tower" and list(tf.markers) == [17] and tf.markers[17].shape == (4, 3)
    write_testfield(tmp_path / "again.json", tf)
    again = read_testfield(tmp_path / "again.json")
    assert (again.markers[17] == tf.markers[17]).all() and again.sigma_mm == 0.05
    ids, corners = tf.corners()
    assert ids.tolist() == [17] and corners.shape == (1, 4, 3)


def test_it_rejects_an_unknown_dictionary(tmp_path):
    with pytest.raises(FormatError, match="aruco_dictionary 'DICT_9X9_7'"):
        read_testfield(write(tmp_path / "tf.json", {**GOOD, "aruco_dictionary": "DICT_9X9_7"}))


def test_it_rejects_a_marker_with_three_corners(tmp_path):
    with pytest.raises(FormatError, match="marker 17"):
        read_testfield(write(tmp_path / "tf.json", {**GOOD, "markers": {"17": [[0, 0, 0]] * 3}}))


def test_it_rejects_a_non_integer_marker_id(tmp_path):
    with pytest.raises(FormatError, match="marker id 'x1'"):
        read_testfield(write(tmp_path / "tf.json", {**GOOD, "markers": {"x1": GOOD["markers"]["17"]}}))


def test_it_rejects_missing_sigma(tmp_path):
    obj = dict(GOOD)
    obj.pop("sigma_mm")
    with pytest.raises(FormatError, match="tf.json: missing required key 'sigma_mm'"):
        read_testfield(write(tmp_path / "tf.json", obj))


def test_testfield_is_not_collected_as_a_test():
    assert TestField.__test__ is False
