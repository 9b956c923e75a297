"""After LOGIN_FAILURE_LIMIT failed sign-ins an account is locked out, on the pages' sign-in and the admin's."""

import pytest


def _fail(client, url, username, times):
    return [client.post(url, {"username": username, "password": "wrong"}) for _ in range(times)]


@pytest.mark.django_db
def test_it_locks_the_account_out_and_says_so(client, charlie, settings):
    answers = _fail(client, "/accounts/login/", "charlie", settings.AXES_FAILURE_LIMIT)
    assert [r.status_code for r in answers[:-1]] == [200] * (settings.AXES_FAILURE_LIMIT - 1)
    assert answers[-1].status_code == 429 and b"Too many failed sign-ins" in answers[-1].content
    # the right password does not help while locked, from a fresh browser either
    from django.test import Client

    r = Client().post("/accounts/login/", {"username": "charlie", "password": "pw-charlie"})
    assert r.status_code == 429 and b"locked" in r.content
    assert "_auth_user_id" not in client.session


@pytest.mark.django_db
def test_a_success_before_the_limit_clears_the_failures(client, charlie, settings):
    _fail(client, "/accounts/login/", "charlie", settings.AXES_FAILURE_LIMIT - 1)
    assert client.post("/accounts/login/", {"username": "charlie", "password": "pw-charlie"}).status_code == 302
    client.logout()
    assert _fail(client, "/accounts/login/", "charlie", 1)[0].status_code == 200


@pytest.mark.django_db
def test_it_locks_out_on_the_admin_sign_in_too(client, admin_user, settings):
    answers = _fail(client, "/admin/login/", admin_user.username, settings.AXES_FAILURE_LIMIT)
    assert answers[-1].status_code == 429 and b"Too many failed sign-ins" in answers[-1].content
    r = client.post("/admin/login/", {"username": admin_user.username, "password": "password"})
    assert r.status_code == 429
