"""A patient's page carries a CSP, no-store, X-Frame-Options DENY and a Referrer-Policy; so does the API."""

import pytest

from clinic.models import Patient


@pytest.mark.django_db
def test_it_sends_the_security_headers_on_a_patient_page(client, charlie, clinic):
    p = Patient.objects.create(clinic=clinic, identifier="P-1", name="Robin")
    client.force_login(charlie)
    r = client.get(f"/patients/{p.pk}/")
    assert r.status_code == 200 and b"Robin" in r.content
    csp = r["Content-Security-Policy"]
    assert "default-src 'self'" in csp and "img-src 'self' data:" in csp and "unsafe-inline" not in csp
    assert "no-store" in r["Cache-Control"]
    assert r["X-Frame-Options"] == "DENY"
    assert r["Referrer-Policy"] == "same-origin"
    assert b"<script" not in r.content and b"<style" not in r.content and b'style="' not in r.content


@pytest.mark.django_db
def test_it_keeps_the_api_out_of_caches(client, charlie, clinic):
    client.force_login(charlie)
    r = client.post("/api/patients", {"clinic": clinic.pk, "identifier": "P-2", "name": "Sam"},
                    content_type="application/json")
    assert r.status_code == 201 and "no-store" in r["Cache-Control"]


@pytest.mark.django_db
def test_the_api_docs_run_no_inline_script(client):
    r = client.get("/api/docs")
    assert r.status_code == 200
    body = r.content.decode()
    assert "cdn." not in body
    scripts = body.split("<script")[1:]
    assert scripts and all(' src="' in s.split(">")[0] or 'type="application/json"' in s.split(">")[0]
                           for s in scripts)


@pytest.mark.django_db
def test_the_stylesheet_is_served_as_a_static_file(client):
    r = client.get("/static/clinic/site.css")
    assert r.status_code == 200 and b"font-family" in b"".join(r.streaming_content)
