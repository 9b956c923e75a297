import pytest


@pytest.mark.django_db
def test_it_reports_the_database(client):
    r = client.get("/healthz")
    assert r.status_code == 200
    assert r.json() == {"status": "ok", "database": True}
