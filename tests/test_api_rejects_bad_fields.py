"""Every field of every API body is checked before the database sees it: a 4xx naming the field, nothing stored.

PostgreSQL refuses a NUL character and a string longer than its column, and 32-bit columns overflow: each of
those was a 500 there (and stored as it came by SQLite). A rig serial with a "/" broke the home page.
"""

import copy
import json

import pytest

from clinic.models import CaptureSession, Patient, Rig, Visit
from tests.api_helpers import auth, small_bundle
from tests.boundary_fixtures import RIG

HUGE = 2**70


def _named(r, field) -> bool:
    """The answer is a 4xx whose JSON names ``field`` (ninja's 422 lists it in ``loc``; a 400 in its detail)."""
    return 400 <= r.status_code < 500 and field in json.dumps(r.json())


def _post(client, path, body, **extra):
    return client.post(path, data=json.dumps(body), content_type="application/json", **extra)


@pytest.mark.django_db
@pytest.mark.parametrize("field, value", [
    ("identifier", ""), ("identifier", "   "), ("identifier", "P" * 65), ("identifier", "P-1\x00"),
    ("name", ""), ("name", "n" * 201), ("name", "Ro\x00bin"),
    ("date_of_birth", "2020-13-45"), ("date_of_birth", "yesterday"), ("date_of_birth", "2999-01-01"),
    ("sex", "Q"), ("sex", "female"), ("notes", "ok\x00"), ("notes", "n" * 20_001),
    ("clinic", HUGE), ("clinic", 0), ("clinic", "one"),
])
def test_a_bad_patient_field_is_refused_and_nothing_is_stored(client, charlie, clinic, field, value):
    client.force_login(charlie)
    body = {"clinic": clinic.pk, "identifier": "P-1", "name": "Robin", "date_of_birth": "2014-05-01", "sex": "F",
            field: value}
    r = _post(client, "/api/patients", body)
    assert _named(r, field), (r.status_code, r.content[:300])
    assert Patient.objects.count() == 0


@pytest.mark.django_db
def test_a_good_patient_is_stored_with_its_names_trimmed(client, charlie, clinic):
    client.force_login(charlie)
    r = _post(client, "/api/patients", {"clinic": clinic.pk, "identifier": " P-1 ", "name": "Robin",
                                        "date_of_birth": "2014-05-01", "sex": "X"})
    assert r.status_code == 201
    assert Patient.objects.get().identifier == "P-1"


@pytest.mark.django_db
@pytest.mark.parametrize("field, value", [
    ("date", "2026-02-30"), ("date", "soon"), ("date", "2010-01-01"),  # the last: before the date of birth
    ("reason", "r" * 201), ("reason", "a\x00"), ("notes", "\x00"),
])
def test_a_bad_visit_field_is_refused_and_nothing_is_stored(client, charlie, clinic, field, value):
    patient = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin", date_of_birth="2014-05-01")
    client.force_login(charlie)
    r = _post(client, f"/api/patients/{patient.pk}/visits", {"date": "2026-01-10", field: value})
    assert _named(r, field), (r.status_code, r.content[:300])
    assert Visit.objects.count() == 0


@pytest.mark.django_db
def test_a_patient_id_beyond_any_database_id_is_refused(client, charlie):
    client.force_login(charlie)
    r = _post(client, f"/api/patients/{HUGE}/visits", {})
    assert _named(r, "patient_id"), (r.status_code, r.content[:300])


def _rig(**changes):
    rig = copy.deepcopy(RIG)
    rig["serial"] = "RIG-NEW"
    for path, value in changes.items():
        target = rig
        *parents, last = path.split(".")
        for p in parents:
            target = target[p]
        target[last] = value
    return rig


@pytest.mark.django_db
@pytest.mark.parametrize("body, field", [
    ({"rig": _rig(serial="RIG/7")}, "RIG/7"),
    ({"rig": _rig(serial="../etc")}, "../etc"),
    ({"rig": _rig(serial="R" * 65)}, "serial"),
    ({"rig": _rig(serial="RIG 7")}, "RIG 7"),
    ({"rig": _rig(**{"cameras.A1.width": 10**9})}, "width"),
    ({"rig": _rig(**{"cameras.A1.model": "m" * 201})}, "model"),
    ({"rig": _rig(**{"cameras.A1.model": "m\x00"})}, "model"),
    ({"rig": _rig(**{"arms": [{"id": "A" * 33, "cameras": ["A1", "A2", "B1"], "projector": "P"}]})}, "arm id"),
    ({"recalibration_interval_days": 0}, "recalibration_interval_days"),
    ({"recalibration_interval_days": -30}, "recalibration_interval_days"),
    ({"recalibration_interval_days": HUGE}, "recalibration_interval_days"),
    ({"poses_per_calibration": 0}, "poses_per_calibration"),
    ({"poses_per_calibration": 10**6}, "poses_per_calibration"),
])
def test_a_bad_rig_registration_is_refused_and_nothing_is_stored(client, alice, clinic, body, field):
    client.force_login(alice)
    r = _post(client, "/api/rigs", {"clinic": clinic.pk, "rig": _rig(), **body})
    assert _named(r, field), (r.status_code, r.content[:300])
    assert not Rig.objects.exists()


@pytest.mark.django_db
def test_a_safe_serial_is_registered(client, alice, clinic):
    client.force_login(alice)
    r = _post(client, "/api/rigs", {"clinic": clinic.pk, "rig": _rig(serial="TS-2026.04_b")})
    assert r.status_code == 201 and Rig.objects.get().serial == "TS-2026.04_b"


@pytest.mark.django_db
@pytest.mark.parametrize("change, field", [
    ({"captured_at": "last tuesday"}, "captured_at"),
    ({"captured_at": "2026-11-22T09:30:00\x00"}, "captured_at"),
    ({"captured_at": "2026-11-22T09:30:00+00:00" + " " * 60}, "captured_at"),
    ({"operator": "a\x00b"}, "operator"),
    ({"pose": 10**12}, "pose"),
])
def test_a_bad_manifest_field_is_refused_and_nothing_is_stored(client, small_rig, tmp_path, change, field):
    _, key = small_rig
    manifest = json.loads((small_bundle(tmp_path, kind="testfield") / "capture.json").read_text())
    manifest.update(change)
    r = _post(client, "/api/sessions", {"manifest": manifest}, **auth(key))
    assert _named(r, field), (r.status_code, r.content[:300])
    assert not CaptureSession.objects.exists()


@pytest.mark.django_db
@pytest.mark.parametrize("extra, field", [
    ({"poses": 0}, "poses"), ({"poses": HUGE}, "poses"), ({"visit": HUGE}, "visit"), ({"visit": -1}, "visit"),
    ({"calibration_set": "s" * 101}, "calibration_set"), ({"calibration_set": "set\x00"}, "calibration_set"),
    ({"calibration_set": ""}, "calibration_set"),
])
def test_a_bad_session_field_is_refused_and_nothing_is_stored(client, small_rig, tmp_path, extra, field):
    _, key = small_rig
    manifest = json.loads((small_bundle(tmp_path, kind="testfield") / "capture.json").read_text())
    r = _post(client, "/api/sessions", {"manifest": manifest, **extra}, **auth(key))
    assert _named(r, field), (r.status_code, r.content[:300])
    assert not CaptureSession.objects.exists()


@pytest.mark.django_db
def test_an_idempotency_key_longer_than_its_column_is_refused(client, small_rig, tmp_path):
    _, key = small_rig
    manifest = json.loads((small_bundle(tmp_path) / "capture.json").read_text())
    r = _post(client, "/api/sessions", {"manifest": manifest}, HTTP_IDEMPOTENCY_KEY="k" * 201, **auth(key))
    assert _named(r, "Idempotency-Key"), (r.status_code, r.content[:300])
    assert not CaptureSession.objects.exists()


@pytest.mark.django_db
@pytest.mark.parametrize("query, field", [("poses=0", "poses"), (f"visit={HUGE}", "visit"),
                                          ("calibration_set=" + "s" * 101, "calibration_set")])
def test_a_bad_bundle_query_is_refused(client, small_rig, query, field):
    _, key = small_rig
    r = client.post(f"/api/bundles?{query}", data=b"PK", content_type="application/zip", **auth(key))
    assert _named(r, field), (r.status_code, r.content[:300])


@pytest.mark.django_db
@pytest.mark.parametrize("path", ["/api/rigs/RIG-T%00/keys", "/api/rigs/RIG-T/keys/tsk%00"])
def test_a_nul_in_a_path_is_refused(client, alice, small_rig, path):
    client.force_login(alice)
    r = client.delete(path) if path.count("/") == 5 else client.post(path)
    assert 400 <= r.status_code < 500 and "NUL" in r.json()["detail"], (r.status_code, r.content[:300])


@pytest.mark.django_db
def test_a_nul_in_a_camera_name_is_refused(client, small_rig, tmp_path):
    from tests.api_helpers import open_session, put

    _, key = small_rig
    sid = open_session(client, key, small_bundle(tmp_path)).json()["id"]
    r = put(client, key, sid, "A1%00", b"x")
    assert r.status_code == 400 and "camera" in r.json()["detail"]


@pytest.mark.django_db
def test_a_testfield_with_a_nul_is_refused(client, alice, clinic):
    client.force_login(alice)
    r = _post(client, "/api/testfields", {"clinic": clinic.pk, "testfield": {"format": "x", "name": "t\x00"}})
    assert _named(r, "name"), (r.status_code, r.content[:300])
