"""docker/ stays consistent with the repository (no Docker engine runs here)."""

import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def test_compose_file_names_the_services_a_clinic_runs():
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    services = compose["services"]
    assert {"web", "worker", "beat", "postgres", "redis"} <= set(services)
    for name in ("web", "worker", "beat"):
        env = services[name]["environment"]
        assert env["DATABASE_URL"].startswith("postgres://") and env["CELERY_BROKER_URL"].startswith("redis://")
        assert services[name]["build"]["dockerfile"] == "docker/Dockerfile"


def test_dockerfile_copies_only_what_exists():
    text = (ROOT / "docker" / "Dockerfile").read_text()
    for src in re.findall(r"^COPY (.+) \S+$", text, flags=re.M):
        for item in src.split():
            assert (ROOT / item).exists(), f"Dockerfile copies {item}, which does not exist"


def test_the_web_app_is_reached_only_through_the_buffering_proxy():
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    services = compose["services"]
    assert "ports" not in services["web"] and services["web"]["environment"]["SECURE_PROXY_SSL_HEADER"]
    proxy = services["proxy"]
    mounted = [v.split(":")[0] for v in proxy["volumes"]]
    assert "./nginx.conf" in mounted and (ROOT / "docker" / "nginx.conf").exists()
    assert "./proxy.conf" in mounted
    conf = (ROOT / "docker" / "nginx.conf").read_text() + (ROOT / "docker" / "proxy.conf").read_text()
    for directive in ("client_header_timeout", "proxy_request_buffering on", "client_max_body_size",
                      "X-Forwarded-Proto https", "listen 443 ssl", "include /etc/nginx/torsoscan-proxy.conf"):
        assert directive in conf, directive
