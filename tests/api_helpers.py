"""Small helpers of the API's bad-input tests (the small rig of ``boundary_fixtures``)."""

import json
from pathlib import Path

from tests.boundary_fixtures import bundle


def auth(key):
    return {"HTTP_AUTHORIZATION": f"Bearer {key}"}


def open_session(client, key, folder: Path, **extra):
    manifest = json.loads((folder / "capture.json").read_text())
    return client.post("/api/sessions", data=json.dumps({"manifest": manifest, **extra}),
                       content_type="application/json", **auth(key))


def put(client, key, session_id, camera, data: bytes):
    return client.put(f"/api/sessions/{session_id}/images/{camera}", data=data,
                      content_type="application/octet-stream", **auth(key))


def image_bytes(folder: Path, camera: str) -> bytes:
    return (folder / "images" / f"{camera}.png").read_bytes()


def small_bundle(tmp_path, name="cap", **kw) -> Path:
    return bundle(tmp_path / name, **kw)
