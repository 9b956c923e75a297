"""The API documents itself; the admin shows every record."""

import pytest


@pytest.mark.django_db
def test_the_openapi_document_lists_the_rig_endpoints(client):
    doc = client.get("/api/openapi.json").json()
    paths = doc["paths"]
    for p in ("/api/sessions", "/api/sessions/{session_id}/images/{camera}", "/api/sessions/{session_id}/finalize",
              "/api/bundles", "/api/jobs/{job_id}", "/api/jobs/{job_id}/files/{name}"):
        assert p in paths, p


@pytest.mark.django_db
def test_every_admin_list_page_opens(admin_client, small_rig):
    from django.contrib import admin

    for model in admin.site._registry:
        if model._meta.app_label != "clinic":
            continue
        url = f"/admin/clinic/{model._meta.model_name}/"
        assert admin_client.get(url).status_code == 200, url
