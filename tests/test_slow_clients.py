"""Slow or stalled clients cannot block the web app: nginx (docker/proxy.conf) buffers requests for gunicorn.

Two connections that never finish their headers take both of gunicorn's sync workers when they reach it
directly; through nginx, with the production proxy settings, a third client is still answered at once.
"""

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port, timeout=30.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"nothing listens on {port}")


def _get(port, timeout):
    """Seconds a GET /healthz takes, or None when it does not answer within ``timeout``."""
    t0 = time.monotonic()
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
            data = s.recv(64)
        return time.monotonic() - t0 if data.startswith(b"HTTP/1.") else None
    except OSError:
        return None


def _stall(port, n):
    """``n`` connections that send half a request line and then nothing."""
    out = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: loc")
        out.append(s)
    return out


@pytest.fixture
def servers(tmp_path):
    nginx = shutil.which("nginx") or "/usr/sbin/nginx"
    if not os.path.exists(nginx):
        message = "nginx is not installed (make test installs it)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    g_port, n_port = _free_port(), _free_port()
    env = {**os.environ, "DEBUG": "true", "TORSOSCAN_VAR": str(tmp_path), "ALLOWED_HOSTS": "localhost,127.0.0.1"}
    gunicorn = subprocess.Popen(
        [sys.executable, "-m", "gunicorn", "clinic.wsgi:application", "--bind", f"127.0.0.1:{g_port}",
         "--workers", "2", "--timeout", "30"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)
    conf = tmp_path / "nginx.conf"
    conf.write_text(f"""
daemon off;
pid {tmp_path}/nginx.pid;
error_log {tmp_path}/error.log;
worker_processes 1;
events {{ worker_connections 256; }}
http {{
    access_log off;
    client_body_temp_path {tmp_path}/body;
    proxy_temp_path {tmp_path}/proxy;
    fastcgi_temp_path {tmp_path}/fastcgi;
    uwsgi_temp_path {tmp_path}/uwsgi;
    scgi_temp_path {tmp_path}/scgi;
    include {ROOT}/docker/proxy.conf;
    server {{
        listen 127.0.0.1:{n_port};
        location / {{ proxy_pass http://127.0.0.1:{g_port}; }}
    }}
}}
""")
    proxy = subprocess.Popen([nginx, "-c", str(conf), "-e", str(tmp_path / "error.log")], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    try:
        _wait_port(g_port)
        _wait_port(n_port)
        assert _get(g_port, 20) is not None  # the app answers (first request loads Django)
        yield g_port, n_port
    finally:
        for p in (proxy, gunicorn):
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def test_two_stalled_clients_block_gunicorn_alone_but_not_through_the_proxy(servers):
    g_port, n_port = servers
    stalled = _stall(n_port, 2)
    try:
        t = _get(n_port, 5)
        assert t is not None and t < 2.0, f"through nginx a third client waited {t} s"
    finally:
        for s in stalled:
            s.close()
    # the same two stalled clients straight at gunicorn take both of its workers: nobody else is answered
    stalled = _stall(g_port, 2)
    try:
        assert _get(g_port, 3) is None
    finally:
        for s in stalled:
            s.close()
