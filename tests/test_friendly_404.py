"""A page that is not there (or not the user's) answers with a friendly page that keeps the navigation."""

import pytest


@pytest.mark.django_db
def test_the_404_page_keeps_the_navigation(client, charlie, settings):
    settings.DEBUG = False  # Django's technical 404 otherwise
    client.force_login(charlie)
    r = client.get("/patients/999999/")
    assert r.status_code == 404
    html = r.content.decode()
    assert "<h1>Not found</h1>" in html
    assert 'href="/"' in html and ">Patients</a>" in html and "Sign out" in html
    assert 'class="skip" href="#main"' in html
    assert b"<style" not in r.content and b'style="' not in r.content


def test_the_500_page_renders_without_a_request():
    from django.template import loader

    html = loader.get_template("500.html").render({})
    assert "Something went wrong" in html and ">Patients</a>" in html
