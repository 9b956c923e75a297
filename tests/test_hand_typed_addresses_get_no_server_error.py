"""Addresses typed by hand (an id too long for the database, a key prefix or a serial too long, a NUL) get a
404 or a 400 naming what is wrong, never a server error."""

import pytest


@pytest.mark.django_db
def test_it_answers_404_for_an_id_too_long_for_the_database(client, ada, clinic):
    client.force_login(ada)
    client.raise_request_exception = False
    huge = "9" * 30
    for url in (f"/patients/{huge}/", f"/visits/{huge}/", f"/clinics/{huge}/members/"):
        assert client.get(url).status_code == 404, url
    assert client.post(f"/clinics/{huge}/members/add", {"username": "x", "role": "clinician"}).status_code == 404


@pytest.mark.django_db
def test_it_names_the_field_of_a_key_prefix_too_long(client, ada, small_rig):
    rig, _ = small_rig
    client.force_login(ada)
    client.raise_request_exception = False
    r = client.post(f"/rigs/{rig.serial}/keys/{'p' * 40}/revoke")
    assert r.status_code == 400 and "prefix" in r.content.decode(), r.status_code


@pytest.mark.django_db
def test_it_does_not_echo_a_forged_host_or_name_a_setting(client):
    client.raise_request_exception = False
    r = client.get("/", HTTP_HOST="evil.example")
    html = r.content.decode()
    assert r.status_code == 400 and "could not be understood" in html
    assert "evil.example" not in html and "ALLOWED_HOSTS" not in html
