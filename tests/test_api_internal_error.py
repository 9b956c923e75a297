"""A defect in an API view is a JSON 500 with an id, and the log has its traceback under the same id."""

import logging

import pytest

from tests.api_helpers import auth, open_session, small_bundle


@pytest.mark.django_db
def test_an_unexpected_error_is_json_and_logged_with_its_traceback(client, small_rig, tmp_path, monkeypatch,
                                                                   caplog):
    import clinic.api

    def broken(session):
        raise KeyError("a defect in the view")

    monkeypatch.setattr(clinic.api, "_session_out", broken)
    _, key = small_rig
    with caplog.at_level(logging.ERROR, logger="clinic.api"):
        r = open_session(client, key, small_bundle(tmp_path))
    assert r.status_code == 500 and r["Content-Type"].startswith("application/json")
    body = r.json()
    assert body["detail"] == "internal error" and len(body["id"]) == 8
    (record,) = [rec for rec in caplog.records if rec.name == "clinic.api" and body["id"] in rec.getMessage()]
    assert record.exc_info and record.exc_info[0] is KeyError
    assert "a defect in the view" in caplog.text and "Traceback" in caplog.text


@pytest.mark.django_db
def test_expected_refusals_keep_their_status(client, small_rig):
    # the catch-all must not swallow ninja's own answers: a missing key is still a 401, a bad id a 404
    _, key = small_rig
    assert client.get("/api/sessions/not-a-uuid").status_code == 401
    assert client.get("/api/sessions/not-a-uuid", **auth(key)).status_code == 404
