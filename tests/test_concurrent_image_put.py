"""The same image PUT by two clients at once (real PostgreSQL, a threaded gunicorn): stored once, no 500, no
file left behind. Both uploads are held until both have passed every check and are about to store the image
(tests/fault_storage.py), so they really race for the row."""

import json
import threading

from tests.api_helpers import image_bytes, small_bundle
from tests.pg_server import pg_server


def test_two_puts_of_one_image_at_once_store_it_once(tmp_path):
    folder = small_bundle(tmp_path)
    with pg_server(tmp_path) as server:
        manifest = json.loads((folder / "capture.json").read_text())
        r = server.api.call("POST", "/api/sessions", json_body={"manifest": manifest}, key=server.key)
        assert r.status == 201, r.content
        sid = r.json()["id"]
        server.arm("barrier")
        answers = []

        def put():
            answers.append(server.api.call("PUT", f"/api/sessions/{sid}/images/A1", data=image_bytes(folder, "A1"),
                                           key=server.key, content_type="application/octet-stream"))

        clients = [threading.Thread(target=put) for _ in range(2)]
        for c in clients:
            c.start()
        for c in clients:
            c.join(timeout=60)
        assert sorted(a.status for a in answers) == [200, 201], [(a.status, a.content) for a in answers]
        assert sorted(a.json()["stored"] for a in answers) == ["already", "now"]
        (stored,), = server.sql("SELECT file FROM clinic_captureimage WHERE camera = 'A1'")
        assert server.media_files() == [stored], "the losing upload's file was left behind (or the winner's deleted)"
        assert (server.var / "media" / stored).read_bytes() == image_bytes(folder, "A1")
