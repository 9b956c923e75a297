"""A signed-in session ends after SESSION_IDLE_MINUTES without a request, without a database write per page
refresh: its expiry moves forward at most once every SESSION_REFRESH_SECONDS."""

from datetime import timedelta

import pytest
from django.contrib.sessions.models import Session
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.utils import timezone


def session_writes(client, path="/"):
    with CaptureQueriesContext(connection) as queries:
        r = client.get(path)
    assert r.status_code == 200, r.status_code
    return [q["sql"] for q in queries if "django_session" in q["sql"]
            and q["sql"].lstrip().upper().startswith(("INSERT", "UPDATE", "DELETE"))]


@pytest.mark.django_db
def test_a_page_refresh_writes_the_session_at_most_once_a_minute(client, charlie):
    client.force_login(charlie)
    session_writes(client)  # the first request after signing in may move the expiry
    for _ in range(3):
        assert session_writes(client) == [], "a page refresh wrote the session"


@pytest.mark.django_db
def test_a_request_after_the_interval_moves_the_expiry_forward(client, charlie, settings):
    client.force_login(charlie)
    session_writes(client)
    key = client.session.session_key
    Session.objects.filter(pk=key).update(expire_date=timezone.now() + timedelta(minutes=1))
    settings.SESSION_REFRESH_SECONDS = 0
    assert session_writes(client), "the expiry was not moved"
    left = Session.objects.get(pk=key).expire_date - timezone.now()
    assert timedelta(seconds=settings.SESSION_COOKIE_AGE - 30) < left <= timedelta(seconds=settings.SESSION_COOKIE_AGE)


@pytest.mark.django_db
def test_it_signs_out_a_session_idle_longer_than_the_timeout(client, charlie):
    client.force_login(charlie)
    assert client.get("/").status_code == 200
    Session.objects.filter(pk=client.session.session_key).update(expire_date=timezone.now() - timedelta(seconds=1))
    r = client.get("/")
    assert r.status_code == 302 and "/accounts/login/" in r["Location"]
