"""A database restart leaves the server's kept connections dead: the next request reconnects, never a 500 or a
503 (CONN_HEALTH_CHECKS). Every backend of the test's database is terminated between two requests, as a
restart does, on a server whose single thread keeps its connection between requests (CONN_MAX_AGE)."""

import json

from tests.api_helpers import small_bundle
from tests.pg_server import pg_server


def test_the_request_after_the_database_restarted_is_answered(tmp_path):
    folder = small_bundle(tmp_path)
    with pg_server(tmp_path, threads=1, DB_CONN_MAX_AGE="600") as server:
        manifest = json.loads((folder / "capture.json").read_text())
        sid = server.api.call("POST", "/api/sessions", json_body={"manifest": manifest}, key=server.key).json()["id"]
        assert server.api.call("GET", f"/api/sessions/{sid}", key=server.key).status == 200
        assert server.terminate_connections() >= 1, "the server kept no connection to terminate"
        r = server.api.call("GET", f"/api/sessions/{sid}", key=server.key)
        assert r.status == 200, (r.status, r.content)
        server.terminate_connections()
        server.api.login("alice", "pw-alice")  # a page (the sign-in) after the restart too
        assert server.api.call("GET", "/").status == 200
