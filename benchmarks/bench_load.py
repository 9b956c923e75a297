"""Load on loopback: N rigs uploading paper-scale captures at once while 50 clients poll; every image stored once?

Starts gunicorn (``--workers 2``, gthread ``--threads``) on a fresh
PostgreSQL database, with a redis-server of its own as the broker (no worker:
the finalized sessions' jobs stay queued; only the web side is measured).
Registers N rigs of 20 cameras of 3000 x 2000 px. Their images are cheap
stand-ins, not a simulation: one grey PNG per camera (a projected-dot-like
random pattern with sensor noise), made once; each rig's copy differs by a text
chunk naming the rig, so every upload has its own sha256 and the server hashes,
decodes and stores each. Then, all at once:

- every rig opens a session, PUTs its 20 images one after the other and finalizes;
- 50 clients poll a session's status (``GET /api/sessions/<id>``), one request a second each.

Reports the upload throughput (MB/s over the whole upload phase), p50 / p95 /
max latency of the image PUTs and of the polls, and checks that every image
is stored exactly once with its sha256 (and no other file is in the store).

    .venv/bin/python benchmarks/bench_load.py [--rigs 20] [--pollers 50] [--threads 8]
"""

import argparse
import hashlib
import http.client
import json
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
import uuid
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("DEBUG", "true")  # plain HTTP on loopback (DEBUG off wants HTTPS and a real SECRET_KEY)

from tests.outage import OwnRedis  # noqa: E402
from tests.pg_server import run_manage, run_sql  # noqa: E402
from tests.service_flow import free_port, stop_processes, wait_for_port  # noqa: E402

WIDTH, HEIGHT = 3000, 2000
CAMERAS = [f"{arm}{i}" for arm in "ABCD" for i in range(1, 6)]


def rig_json(serial: str) -> dict:
    return {"format": "torso-rig/1", "serial": serial,
            "arms": [{"id": arm, "cameras": [f"{arm}{i}" for i in range(1, 6)], "projector": f"P{arm}"}
                     for arm in "ABCD"],
            "cameras": {c: {"width": WIDTH, "height": HEIGHT, "pixel_size_mm": 0.0039, "nominal_focal_mm": 12.0,
                            "model": "load"} for c in CAMERAS}}


def base_png(seed: int) -> bytes:
    """A 3000 x 2000 grey PNG: random 4-px dots (a projected pattern) plus sensor noise."""
    import cv2

    rng = np.random.default_rng(seed)
    dots = rng.integers(0, 2, (HEIGHT // 4, WIDTH // 4), dtype=np.uint8) * 120 + 60
    img = np.repeat(np.repeat(dots, 4, axis=0), 4, axis=1)
    img = (img + rng.integers(0, 8, img.shape, dtype=np.uint8)).astype(np.uint8)
    return cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1].tobytes()


def with_text(png: bytes, text: str) -> bytes:
    """The same image with a tEXt chunk after the header: other bytes, other sha256, same pixels."""
    data = b"Comment\x00" + text.encode()
    chunk = struct.pack(">I", len(data)) + b"tEXt" + data + struct.pack(">I", zlib.crc32(b"tEXt" + data))
    return png[:33] + chunk + png[33:]  # 8-byte signature + 25-byte IHDR chunk


def percentile(values, q):
    return float(np.percentile(values, q)) if values else float("nan")


class Http:
    def __init__(self, port):
        self.port = port

    def call(self, method, path, key, body=None, headers=None):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=600)
        try:
            hdrs = {"Authorization": f"Bearer {key}", **(headers or {})}
            if body is not None:
                hdrs["Content-Length"] = str(len(body))
            conn.request(method, path, body=body, headers=hdrs)
            r = conn.getresponse()
            return r.status, r.read()
        finally:
            conn.close()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rigs", type=int, default=20)
    parser.add_argument("--pollers", type=int, default=50)
    parser.add_argument("--threads", type=int, default=8, help="gunicorn threads per worker (2 workers)")
    parser.add_argument("--work", type=Path, default=ROOT / "bench-out" / "load")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    run = Path(tempfile.mkdtemp(prefix="run-", dir=args.work))

    t = time.time()
    bases = []
    for i in range(len(CAMERAS)):  # kept for the next run: making them takes a minute
        cached = args.work / f"base-{i}.png"
        if not cached.exists():
            cached.write_bytes(base_png(i))
        bases.append(cached.read_bytes())
    print(f"20 base images, {sum(map(len, bases)) / 1e6:.0f} MB a capture ({time.time() - t:.0f} s)", flush=True)

    broker = OwnRedis(run / "redis")
    broker.start()
    dbname = f"torsoscan_load_{os.getpid()}"
    run_sql(f'CREATE DATABASE "{dbname}"')
    env = {**os.environ, "DJANGO_SETTINGS_MODULE": "clinic.settings", "TORSOSCAN_VAR": str(run / "var"),
           "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{dbname}", "CELERY_BROKER_URL": broker.url,
           "CELERY_QUEUE": f"load-{os.getpid()}"}
    server = None
    try:
        run_manage(env, "migrate", "--noinput")
        keys = {f"LOAD-{i:02d}": "tsk_load-" + uuid.uuid4().hex for i in range(args.rigs)}
        seed = ("import json, sys; from django.contrib.auth.models import User;"
                "from clinic.api import sync_cameras; from clinic.models import *; from clinic.models import hash_key;"
                "from recon_engine.formats import rig_from_dict;"
                "c = Clinic.objects.create(name='Load');"
                "v = Visit.objects.create(patient=Patient.objects.create(clinic=c, identifier='P-1', name='Pat'));"
                f"keys = json.loads({json.dumps(json.dumps(keys))}); rigs = json.loads({json.dumps(json.dumps({s: rig_json(s) for s in keys}))});"
                "[sync_cameras(r, rig_from_dict(rigs[r.serial])) or RigKey.objects.create(rig=r, prefix=keys[r.serial][:10], "
                "key_hash=hash_key(keys[r.serial])) for r in [Rig.objects.create(clinic=c, serial=s, description=rigs[s]) "
                "for s in keys]];"
                "print(v.pk)")
        visit = int(run_manage(env, "shell", "-c", seed).split()[-1])
        port = free_port()
        server = subprocess.Popen(
            [sys.executable, "-m", "gunicorn", "clinic.wsgi:application", "--bind", f"127.0.0.1:{port}",
             "--workers", "2", "--worker-class", "gthread", "--threads", str(args.threads), "--timeout", "600"],
            cwd=ROOT, env=env, stdout=open(run / "server.log", "w"), stderr=subprocess.STDOUT)
        wait_for_port(port)
        api = Http(port)

        captures = {}
        for i, serial in enumerate(keys):
            images = {cam: with_text(bases[j], f"{serial} {cam}") for j, cam in enumerate(CAMERAS)}
            manifest = {"format": "torso-capture/1", "kind": "torso", "rig": serial,
                        "captured_at": "2026-12-01T10:00:00+00:00",
                        "images": [{"camera": cam, "file": f"images/{cam}.png",
                                    "sha256": hashlib.sha256(data).hexdigest()} for cam, data in images.items()]}
            captures[serial] = (manifest, images)
        # the pollers' sessions: one per rig, opened before the load (their images never come)
        polled = []
        for serial, (manifest, _) in captures.items():
            status, body = api.call("POST", "/api/sessions", keys[serial],
                                    json.dumps({"manifest": manifest, "visit": visit}).encode(),
                                    {"Content-Type": "application/json", "Idempotency-Key": "poll-" + serial})
            assert status == 201, body[:300]
            polled.append((keys[serial], json.loads(body)["id"]))

        puts, polls, errors = [], [], []
        uploading = threading.Event()
        uploading.set()
        lock = threading.Lock()

        def rig(serial):
            manifest, images = captures[serial]
            status, body = api.call("POST", "/api/sessions", keys[serial],
                                    json.dumps({"manifest": manifest, "visit": visit}).encode(),
                                    {"Content-Type": "application/json", "Idempotency-Key": "load-" + serial})
            if status != 201:
                errors.append(("session", serial, status, body[:200]))
                return
            sid = json.loads(body)["id"]
            for cam, data in images.items():
                t0 = time.time()
                status, body = api.call("PUT", f"/api/sessions/{sid}/images/{cam}", keys[serial], data,
                                        {"Content-Type": "application/octet-stream"})
                with lock:
                    puts.append(time.time() - t0)
                if status != 201:
                    errors.append(("put", serial, cam, status, body[:200]))
            status, body = api.call("POST", f"/api/sessions/{sid}/finalize", keys[serial])
            if status != 200:
                errors.append(("finalize", serial, status, body[:200]))

        def poller(n):
            key, sid = polled[n % len(polled)]
            while uploading.is_set():
                t0 = time.time()
                status, body = api.call("GET", f"/api/sessions/{sid}", key)
                with lock:
                    polls.append(time.time() - t0)
                if status != 200:
                    errors.append(("poll", sid, status, body[:200]))
                time.sleep(max(0.0, 1.0 - (time.time() - t0)))

        pollers = [threading.Thread(target=poller, args=(n,)) for n in range(args.pollers)]
        rigs = [threading.Thread(target=rig, args=(s,)) for s in keys]
        for p in pollers:
            p.start()
        t0 = time.time()
        for r in rigs:
            r.start()
        for r in rigs:
            r.join()
        wall = time.time() - t0
        uploading.clear()
        for p in pollers:
            p.join()

        total = sum(len(d) for _, images in captures.values() for d in images.values())
        # every image stored once, with its sha256; nothing else in the store
        rows = run_sql("SELECT s.idempotency_key, i.camera, i.file FROM clinic_captureimage i "
                    "JOIN clinic_capturesession s ON s.id = i.session_id WHERE s.idempotency_key LIKE 'load-%'",
                    dbname)
        media = run / "var" / "media"
        files = {str(p.relative_to(media)) for p in media.rglob("*") if p.is_file()}
        wrong = [(k, cam) for k, cam, name in rows if not name or hashlib.sha256(
            (media / name).read_bytes()).hexdigest() != hashlib.sha256(captures[k[5:]][1][cam]).hexdigest()]
        extra = files - {name for _, _, name in rows}
        print(f"\n{args.rigs} rigs x 20 images of {WIDTH}x{HEIGHT} px ({total / 1e6:.0f} MB) and {args.pollers} "
              f"pollers; gunicorn 2 workers x {args.threads} threads")
        print(f"upload phase {wall:.1f} s: {total / 1e6 / wall:.1f} MB/s, {len(puts) / wall:.1f} images/s")
        print(f"image PUT latency: p50 {percentile(puts, 50):.2f} s, p95 {percentile(puts, 95):.2f} s, "
              f"max {max(puts):.2f} s ({len(puts)} PUTs)")
        print(f"status poll latency: p50 {percentile(polls, 50) * 1000:.0f} ms, p95 {percentile(polls, 95) * 1000:.0f} "
              f"ms, max {max(polls) * 1000:.0f} ms ({len(polls)} polls, {len(polls) / wall:.1f}/s)")
        print(f"images stored: {len(rows) - len(wrong)} of {args.rigs * 20} with their sha256; "
              f"{len(extra)} other files in the store; {len(errors)} errors")
        for e in errors[:10]:
            print("error:", e)
        return 1 if wrong or extra or errors or len(rows) != args.rigs * 20 else 0
    finally:
        if server is not None:
            stop_processes([server], timeout=30)
        broker.stop()
        run_sql(f'DROP DATABASE IF EXISTS "{dbname}" WITH (FORCE)')


if __name__ == "__main__":
    sys.exit(main())
