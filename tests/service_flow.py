"""The clinic's whole flow through the HTTP API, driven the same way in-process and over a real socket.

``ClientApi`` wraps Django's test client (embedded default: SQLite, jobs
in-process); ``HttpApi`` talks to a real server process over loopback
(PostgreSQL, Redis, a real Celery worker). ``run_flow`` is the clinic's day:
register a rig, calibrate it twice (stability checks), upload a torso image by
image and download the results.
"""

import hashlib
import http.cookiejar
import json
import socket
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Response:
    status: int
    content: bytes

    def json(self):
        return json.loads(self.content)


class ClientApi:
    """Django's test client (in-process)."""

    def __init__(self, client):
        self.client = client

    def login(self, username, password):
        r = self.client.post("/accounts/login/", {"username": username, "password": password})
        assert r.status_code == 302, f"login of {username} failed ({r.status_code})"

    def call(self, method, path, json_body=None, data=None, key=None, headers=None, content_type=None):
        extra = {}
        if key:
            extra["HTTP_AUTHORIZATION"] = f"Bearer {key}"
        for k, v in (headers or {}).items():
            extra["HTTP_" + k.upper().replace("-", "_")] = v
        fn = getattr(self.client, method.lower())
        if json_body is not None:
            r = fn(path, data=json.dumps(json_body), content_type="application/json", **extra)
        elif data is not None:
            r = fn(path, data=data, content_type=content_type or "application/octet-stream", **extra)
        else:
            r = fn(path, **extra)
        content = b"".join(r.streaming_content) if r.streaming else r.content
        return Response(r.status_code, content)


class HttpApi:
    """A server over a real socket (urllib), with a login session and its CSRF token."""

    def __init__(self, base):
        self.base = base.rstrip("/")
        self.jar = http.cookiejar.CookieJar()
        self.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(self.jar),
                                                  _NoRedirect())

    def _csrf(self):
        return next((c.value for c in self.jar if c.name == "csrftoken"), "")

    def login(self, username, password):
        self.call("GET", "/accounts/login/")
        form = urllib.parse.urlencode({"username": username, "password": password,
                                       "csrfmiddlewaretoken": self._csrf()}).encode()
        r = self.call("POST", "/accounts/login/", data=form, content_type="application/x-www-form-urlencoded")
        assert r.status == 302, f"login of {username} failed ({r.status}): {r.content[:300]!r}"

    def call(self, method, path, json_body=None, data=None, key=None, headers=None, content_type=None):
        hdrs = dict(headers or {})
        if json_body is not None:
            data, content_type = json.dumps(json_body).encode(), "application/json"
        if content_type:
            hdrs["Content-Type"] = content_type
        if key:
            hdrs["Authorization"] = f"Bearer {key}"
        elif method != "GET" and self._csrf():
            hdrs["X-CSRFToken"] = self._csrf()
        req = urllib.request.Request(self.base + path, data=data, method=method, headers=hdrs)
        try:
            with self.opener.open(req, timeout=600) as r:
                return Response(r.status, r.read())
        except urllib.error.HTTPError as e:
            return Response(e.code, e.read())


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args, **kwargs):
        return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_port(port: int, tries: int = 300):
    """Until a server listens on ``port`` of loopback (0.1 s between tries)."""
    for _ in range(tries):
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                return
        except OSError:
            time.sleep(0.1)


def stop_processes(procs, timeout=60):
    """Terminate, wait, and kill what does not stop."""
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def upload_capture(api, key, folder: Path, **extra) -> dict:
    """Create the session from the bundle's capture.json, PUT every image, finalize. The session."""
    manifest = json.loads((folder / "capture.json").read_text())
    r = api.call("POST", "/api/sessions", json_body={"manifest": manifest, **extra}, key=key)
    assert r.status == 201, r.content
    sid = r.json()["id"]
    for im in manifest["images"]:
        r = api.call("PUT", f"/api/sessions/{sid}/images/{im['camera']}", data=(folder / im["file"]).read_bytes(),
                     key=key)
        assert r.status == 201, r.content
    r = api.call("POST", f"/api/sessions/{sid}/finalize", key=key)
    assert r.status == 200, r.content
    return r.json()


def upload_unfinalized_capture(api, key, folder: Path) -> str:
    """A capture's manifest and images uploaded but not finalized (in-process, finalizing would run its job at
    once): the session's id."""
    manifest = json.loads((folder / "capture.json").read_text())
    sid = api.call("POST", "/api/sessions", json_body={"manifest": manifest}, key=key).json()["id"]
    for im in manifest["images"]:
        assert api.call("PUT", f"/api/sessions/{sid}/images/{im['camera']}",
                        data=(folder / im["file"]).read_bytes(), key=key).status == 201
    return sid


def finalized_without_its_job(api, key, folder: Path):
    """A capture uploaded and marked finalized in the database, as finalizing would, but with no job run (the
    tests build the job's half-done state themselves): its ``CaptureSession``."""
    from django.utils import timezone

    from clinic.models import CaptureSession

    session = CaptureSession.objects.get(uid=upload_unfinalized_capture(api, key, folder))
    CaptureSession.objects.filter(pk=session.pk).update(state=CaptureSession.FINALIZED, finalized=timezone.now())
    return session


def wait_for_job(api, key, job_id, timeout=900) -> dict:
    t0 = time.time()
    while True:
        job = api.call("GET", f"/api/jobs/{job_id}", key=key).json()
        if job["state"] in ("succeeded", "failed"):
            return job
        assert time.time() - t0 < timeout, f"job {job_id} still {job['state']} ({job['stage']}) after {timeout} s"
        time.sleep(0.5)


def register_rig(api, clinic_id, scenario: Path) -> str:
    tf = json.loads((scenario / "testfield.json").read_text())
    r = api.call("POST", "/api/testfields", json_body={"clinic": clinic_id, "testfield": tf})
    assert r.status in (200, 201), r.content
    rig = json.loads((scenario / "rig.json").read_text())
    r = api.call("POST", "/api/rigs", json_body={"clinic": clinic_id, "rig": rig, "poses_per_calibration": 3})
    assert r.status == 201, r.content
    return r.json()["key"]


def calibrate_set(api, key, scenario: Path, name: str) -> dict:
    """Upload every test-field pose of ``scenario`` as one calibration set; the finished calibration job."""
    poses = sorted((scenario / "captures").glob("testfield-pose*"))
    last = None
    for folder in poses:
        last = upload_capture(api, key, folder, calibration_set=name, poses=len(poses))
    jobs = [j for j in last["jobs"] if j["kind"] == "calibration"]
    assert len(jobs) == 1, last
    return wait_for_job(api, key, jobs[0]["id"])


def run_flow(api, key, clinic_scenario: Path, second_session: Path, visit_id: int, out: Path) -> dict:
    """Calibrate twice, reconstruct a torso; what each step returned."""
    first = calibrate_set(api, key, clinic_scenario, "session-1")
    assert first["state"] == "succeeded", first
    second = calibrate_set(api, key, second_session, "session-2")
    assert second["state"] == "succeeded", second
    torso = upload_capture(api, key, clinic_scenario / "captures" / "visit0-a", visit=visit_id)
    job = wait_for_job(api, key, torso["jobs"][0]["id"])
    assert job["state"] == "succeeded", job
    out.mkdir(parents=True, exist_ok=True)
    for name in ("torso.ply", "report.json", "torso-mesh.ply"):
        r = api.call("GET", f"/api/jobs/{job['id']}/files/{name}", key=key)
        assert r.status == 200, (name, r.content[:200])
        (out / name).write_bytes(r.content)
    r = api.call("GET", f"/api/jobs/{second['id']}/files/calibration.json", key=key)
    assert r.status == 200
    (out / "calibration.json").write_bytes(r.content)
    return {"calibrations": [first, second], "torso_job": job, "session": torso}


_DIRECT = {}


def assert_same_as_engine(out: Path, scenario: Path):
    """The downloaded torso equals what the engine makes directly from the same capture and calibration."""
    from recon_engine.formats import read_calibration, read_capture, read_rig
    from recon_engine.reconstruction import reconstruct_torso
    from recon_engine.surface import read_ply

    rig = read_rig(scenario / "rig.json")
    # both flows (in-process and on a worker) calibrate the same images the same way: the engine's own run on
    # the same calibration is made once (a calibration that differs in any byte is run again)
    key = (str(scenario), sha256(out / "calibration.json"))
    if key not in _DIRECT:
        _DIRECT[key] = reconstruct_torso(read_capture(scenario / "captures" / "visit0-a", rig), rig,
                                         read_calibration(out / "calibration.json"))
    direct = _DIRECT[key]
    served = read_ply(out / "torso.ply")
    report = json.loads((out / "report.json").read_text())
    assert report["points"] == direct["report"]["points"] == len(served["points"])
    np.testing.assert_allclose(served["points"], direct["points"], atol=1e-9)
    assert [p["a"] + p["b"] for p in report["registration"]["pairs"]] == \
           [p["a"] + p["b"] for p in direct["report"]["registration"]["pairs"]]
