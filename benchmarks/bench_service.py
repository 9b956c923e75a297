"""The clinic service under load, over loopback: upload throughput, server memory, polling, jobs per hour.

Starts what a clinic runs (gunicorn with 2 workers, PostgreSQL, Redis, Celery
workers) on a fresh database, registers the scenario's rig through the API,
calibrates it from the scenario's test-field captures (a job), then:

1. uploads the torso capture (20 images at paper scale) image by image and
   reports MB/s and the peak resident memory of every server process
   (``VmHWM``: the kernel's own high-water mark, so no peak is missed);
2. polls a session's status for a while: requests per second, 1 and 4 clients;
3. runs ``--jobs`` reconstruction jobs with 1 and then 2 worker processes
   (concurrency 1 each): jobs per hour.

    .venv/bin/python benchmarks/bench_service.py --scenario bench-out/paper --capture visit0-a
"""

import argparse
import http.client
import json
import os
import secrets
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from provenance import provenance  # noqa: E402
from tests.service_flow import (HttpApi, calibrate_set, free_port, register_rig,  # noqa: E402
                                stop_processes, wait_for_job, wait_for_port)


def peak_rss_mib(pid: int) -> float:
    """Peak resident memory (VmHWM, MiB) of one process."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def children(pid):
    try:
        return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def manage(env, *args):
    r = subprocess.run([sys.executable, "manage.py", *args], cwd=ROOT, env=env, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(r.stderr)
    return r.stdout


def start_workers(env, n, logdir, tag):
    return [subprocess.Popen([sys.executable, "-m", "celery", "-A", "clinic", "worker", "--concurrency", "1",
                              "--loglevel", "warning", "-n", f"bench{k}-{tag}@%h", "--without-gossip",
                              "--without-mingle", "-Q", env["CELERY_QUEUE"]],
                             cwd=ROOT, env=env, stdout=open(logdir / f"worker{k}-{tag}.log", "w"),
                             stderr=subprocess.STDOUT) for k in range(n)]


def upload(api, key, folder, **extra):
    manifest = json.loads((folder / "capture.json").read_text())
    r = api.call("POST", "/api/sessions", json_body={"manifest": manifest, **extra}, key=key,
                 headers={"Idempotency-Key": f"bench-{time.time_ns()}"})
    assert r.status == 201, r.content
    sid = r.json()["id"]
    nbytes, t0 = 0, time.perf_counter()
    for im in manifest["images"]:
        data = (folder / im["file"]).read_bytes()
        nbytes += len(data)
        r = api.call("PUT", f"/api/sessions/{sid}/images/{im['camera']}", data=data, key=key)
        assert r.status == 201, r.content
    seconds = time.perf_counter() - t0
    return sid, nbytes, seconds


def finalize(api, key, sid):
    r = api.call("POST", f"/api/sessions/{sid}/finalize", key=key)
    assert r.status == 200, r.content
    return r.json()["jobs"][0]["id"]


def poll_rate(port, key, sid, clients, seconds=10.0):
    counts = [0] * clients
    stop_at = time.perf_counter() + seconds

    def run(k):
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        while time.perf_counter() < stop_at:
            conn.request("GET", f"/api/sessions/{sid}", headers={"Authorization": f"Bearer {key}"})
            r = conn.getresponse()
            r.read()
            assert r.status == 200
            counts[k] += 1
        conn.close()

    threads = [threading.Thread(target=run, args=(k,)) for k in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return sum(counts) / (time.perf_counter() - t0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", type=Path, required=True)
    ap.add_argument("--capture", default="visit0-a")
    ap.add_argument("--jobs", type=int, default=3, help="reconstruction jobs per worker count (0: upload and polling only)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench-out" / "service.json")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--poll-seconds", type=float, default=10.0, help="how long each polling rate is measured (s)")
    ap.add_argument("--database", default="torsoscan_bench",
                    help="PostgreSQL database to create afresh (dropped first if it exists)")
    args = ap.parse_args(argv)
    import psycopg

    var = args.out.parent / "service-var"  # the server's files, beside the results
    if var.exists():
        import shutil

        shutil.rmtree(var)
    (var / "logs").mkdir(parents=True)
    dbname = args.database
    with psycopg.connect(dbname="postgres", host="127.0.0.1", user="postgres", autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{dbname}" WITH (FORCE)')
        conn.execute(f'CREATE DATABASE "{dbname}"')
    env = {**os.environ, "DATABASE_URL": f"postgres://postgres@127.0.0.1:5432/{dbname}",
           "CELERY_BROKER_URL": "redis://127.0.0.1:6379/14", "CELERY_QUEUE": f"bench-{os.getpid()}",
           "DJANGO_SETTINGS_MODULE": "clinic.settings", "TORSOSCAN_VAR": str(var), "DEBUG": "false",
           "SECRET_KEY": secrets.token_urlsafe(50),  # DEBUG is off: the settings refuse a weak key
           "ALLOWED_HOSTS": "127.0.0.1,localhost",
           # plain HTTP over loopback, as behind a TLS proxy: no redirect to https, cookies sent without TLS
           "SECURE_SSL_REDIRECT": "false", "SESSION_COOKIE_SECURE": "false", "CSRF_COOKIE_SECURE": "false",
           "SECURE_HSTS_SECONDS": "0"}
    manage(env, "migrate", "--noinput")
    manage(env, "shell", "-c",
           "from django.contrib.auth.models import User; from clinic.models import Clinic, Member, Patient, Visit;"
           "c = Clinic.objects.create(name='Bench'); u = User.objects.create_user('tech', '', 'pw-tech');"
           "Member.objects.create(clinic=c, user=u, role='technician');"
           "Visit.objects.create(patient=Patient.objects.create(clinic=c, identifier='B-1', name='Bench'))")
    port = free_port()
    logdir = var / "logs"
    server = subprocess.Popen([sys.executable, "-m", "gunicorn", "clinic.wsgi:application", "--bind",
                               f"127.0.0.1:{port}", "--workers", "2", "--timeout", "600"], cwd=ROOT, env=env,
                              stdout=open(logdir / "server.log", "w"), stderr=subprocess.STDOUT)
    result = {**provenance(__file__, argv), "scenario": str(args.scenario), "capture": args.capture}
    workers = []
    try:
        wait_for_port(port)
        api = HttpApi(f"http://127.0.0.1:{port}")
        api.login("tech", "pw-tech")
        key = register_rig(api, 1, args.scenario)
        if args.jobs:
            workers = start_workers(env, 2, logdir, "cal")
            t0 = time.perf_counter()
            cal = calibrate_set(api, key, args.scenario, "bench")
            result["calibration_job_s"] = round(time.perf_counter() - t0, 1)
            assert cal["state"] == "succeeded", cal
            stop_processes(workers)
            workers = []

        folder = args.scenario / "captures" / args.capture
        sid, nbytes, secs = upload(api, key, folder, visit=1)
        result["upload"] = {"images": len(json.loads((folder / "capture.json").read_text())["images"]),
                            "megabytes": round(nbytes / 1e6, 1), "seconds": round(secs, 2),
                            "megabytes_per_second": round(nbytes / 1e6 / secs, 1),
                            "peak_rss_mib": {
                                name: round(peak_rss_mib(p), 1) for name, p in
                                [("gunicorn master", server.pid)]
                                + [(f"gunicorn worker {k + 1}", c) for k, c in enumerate(children(server.pid))]}}
        print("upload:", result["upload"], flush=True)
        result["polling_requests_per_second"] = {
            str(c): round(poll_rate(port, key, sid, c, args.poll_seconds), 1) for c in (1, 4)}
        print("polling:", result["polling_requests_per_second"], flush=True)

        result["jobs"] = {}
        if not args.jobs:
            return
        sessions = [sid] + [upload(api, key, folder, visit=1)[0] for _ in range(args.jobs * 2 - 1)]
        for n in [int(x) for x in args.workers.split(",")]:
            batch, sessions = sessions[:args.jobs], sessions[args.jobs:]
            workers = start_workers(env, n, logdir, f"w{n}")
            time.sleep(3)
            t0 = time.perf_counter()
            job_ids = [finalize(api, key, s) for s in batch]
            done = [wait_for_job(api, key, j, timeout=7200) for j in job_ids]
            wall = time.perf_counter() - t0
            stop_processes(workers)
            workers = []
            states = [d["state"] for d in done]
            result["jobs"][f"{n}_workers"] = {"jobs": len(batch), "wall_s": round(wall, 1),
                                              "jobs_per_hour": round(3600 * len(batch) / wall, 1),
                                              "states": states}
            print(f"{n} worker(s):", result["jobs"][f"{n}_workers"], flush=True)
    finally:
        stop_processes(workers + [server])
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
        print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
