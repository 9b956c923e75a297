"""A rig's key: required, revocable, and good for its own rig only."""

import pytest

from clinic.models import Rig, RigKey
from tests.api_helpers import auth, open_session, put, small_bundle


@pytest.mark.django_db
def test_it_rejects_a_missing_or_wrong_key(client, small_rig, tmp_path):
    folder = small_bundle(tmp_path)
    assert open_session(client, "", folder).status_code == 401
    assert open_session(client, "tsk_not-a-key", folder).status_code == 401


@pytest.mark.django_db
def test_a_revoked_key_no_longer_works(client, small_rig, tmp_path):
    rig, key = small_rig
    RigKey.objects.filter(rig=rig).update(revoked="2026-11-01T00:00:00Z")
    assert open_session(client, key, small_bundle(tmp_path)).status_code == 401


@pytest.mark.django_db
def test_keys_are_stored_hashed(small_rig):
    rig, key = small_rig
    stored = RigKey.objects.get(rig=rig)
    assert key not in (stored.key_hash, stored.prefix) and key.startswith(stored.prefix)


@pytest.mark.django_db
def test_it_rejects_another_rigs_key(client, small_rig, clinic, tmp_path):
    rig, key = small_rig
    other = Rig.objects.create(clinic=clinic, serial="RIG-OTHER", description={})
    _, other_key = RigKey.issue(other)
    folder = small_bundle(tmp_path)
    r = open_session(client, other_key, folder)
    assert r.status_code == 403 and "RIG-OTHER" in r.json()["detail"] and "RIG-T" in r.json()["detail"]
    sid = open_session(client, key, folder).json()["id"]
    # the other rig's key cannot see or feed this rig's session: as if it did not exist
    assert client.get(f"/api/sessions/{sid}", **auth(other_key)).status_code == 404
    assert put(client, other_key, sid, "A1", b"x").status_code == 404


@pytest.mark.django_db
def test_staff_register_a_rig_and_its_key_is_shown_once(client, alice, clinic):
    from tests.boundary_fixtures import RIG

    client.force_login(alice)
    r = client.post("/api/rigs", data={"clinic": clinic.pk, "rig": {**RIG, "serial": "RIG-NEW"}},
                    content_type="application/json")
    assert r.status_code == 201
    key = r.json()["key"]
    assert RigKey.lookup(key).rig.serial == "RIG-NEW"
    assert Rig.objects.get(serial="RIG-NEW").cameras.count() == 3


@pytest.mark.django_db
def test_users_outside_the_clinic_cannot_register_rigs(client, olga, nobody, charlie, clinic):
    from tests.boundary_fixtures import RIG

    body = {"clinic": clinic.pk, "rig": {**RIG, "serial": "RIG-X"}}
    for user, status in ((olga, 404), (nobody, 404), (charlie, 403)):
        client.force_login(user)
        r = client.post("/api/rigs", data=body, content_type="application/json")
        assert r.status_code == status, user
    assert not Rig.objects.filter(serial="RIG-X").exists()
