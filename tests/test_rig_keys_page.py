"""A clinic administrator issues and revokes their rig's API keys on the rig's page; a new key is shown once."""

import re

import pytest
from django.test import Client

from clinic.models import RigKey


def _rig_answer(key):
    """What the API answers the rig with this key alone (no session): 404 for an unknown session, 401 if refused."""
    return Client().get(f"/api/sessions/{'0' * 32}", HTTP_AUTHORIZATION=f"Bearer {key}").status_code


@pytest.mark.django_db
def test_it_issues_a_key_shown_once_that_the_rig_can_use(client, ada, small_rig):
    rig, _ = small_rig
    client.force_login(ada)
    r = client.post(f"/rigs/{rig.serial}/keys")
    assert r.status_code == 200
    key = re.search(rb'id="new-key">(tsk_[^<]+)<', r.content).group(1).decode()
    assert RigKey.lookup(key).rig == rig
    again = client.get(f"/rigs/{rig.serial}/").content
    assert key.encode() not in again and key[:10].encode() in again  # only its prefix from now on
    assert _rig_answer(key) == 404


@pytest.mark.django_db
def test_it_revokes_a_key(client, ada, small_rig):
    rig, key = small_rig
    client.force_login(ada)
    r = client.post(f"/rigs/{rig.serial}/keys/{key[:10]}/revoke")
    assert r.status_code == 302
    assert RigKey.lookup(key) is None
    assert b"revoked" in client.get(f"/rigs/{rig.serial}/").content
    assert _rig_answer(key) == 401
    # a key already revoked (or never issued) is not found
    assert client.post(f"/rigs/{rig.serial}/keys/{key[:10]}/revoke").status_code == 404


@pytest.mark.django_db
def test_it_refuses_a_clinician(client, charlie, small_rig):
    rig, key = small_rig
    client.force_login(charlie)
    page = client.get(f"/rigs/{rig.serial}/").content
    assert b"Issue a new key" not in page and key[:10].encode() not in page
    assert client.post(f"/rigs/{rig.serial}/keys").status_code == 403
    assert client.post(f"/rigs/{rig.serial}/keys/{key[:10]}/revoke").status_code == 403
    assert rig.keys.count() == 1 and RigKey.lookup(key) is not None
