"""Production settings: a weak SECRET_KEY is refused, `check --deploy` passes with the documented environment."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STRONG = "k3V9-pQ7xZ2mL8rT4wY6nB1cD5fG0hJ_sA9eU3iO7yR2tW6qE8vN4"


def _manage(tmp_path, *args, **env):
    env = {**os.environ, "DEBUG": "false", "SECRET_KEY": STRONG, "ALLOWED_HOSTS": "clinic.example.org",
           "DATABASE_URL": f"sqlite:///{tmp_path}/clinic.sqlite3", "TORSOSCAN_VAR": str(tmp_path / "var"), **env}
    return subprocess.run([sys.executable, "manage.py", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120)


def test_it_passes_check_deploy_with_the_documented_environment(tmp_path):
    r = _manage(tmp_path, "check", "--deploy", "--fail-level", "WARNING")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "no issues" in r.stdout and "WARNING" not in r.stdout + r.stderr


@pytest.mark.parametrize("key", ["", "short-but-random-9f3k", "a" * 60, "ab" * 40,
                                 "django-insecure-" + STRONG, "insecure-development-key-do-not-use-in-production"])
def test_it_refuses_a_weak_secret_key_when_debug_is_off(tmp_path, key):
    r = _manage(tmp_path, "check", SECRET_KEY=key)
    assert r.returncode != 0
    assert "ImproperlyConfigured: SECRET_KEY" in r.stderr


def test_it_allows_the_development_key_with_debug_on(tmp_path):
    r = _manage(tmp_path, "check", DEBUG="true", SECRET_KEY="")
    assert r.returncode == 0, r.stderr


def test_it_turns_https_on_without_debug_and_lets_a_proxy_set_up_say_otherwise(tmp_path):
    code = ("from django.conf import settings as s; print(s.SECURE_SSL_REDIRECT, s.SESSION_COOKIE_SECURE, "
            "s.CSRF_COOKIE_SECURE, s.SECURE_HSTS_SECONDS > 0, s.SECURE_PROXY_SSL_HEADER)")
    assert _manage(tmp_path, "shell", "-v", "0", "-c", code).stdout.split() == ["True", "True", "True", "True", "None"]
    r = _manage(tmp_path, "shell", "-v", "0", "-c", code, SECURE_SSL_REDIRECT="false", SECURE_PROXY_SSL_HEADER="X-Forwarded-Proto")
    assert r.stdout.strip() == "False True True True ('HTTP_X_FORWARDED_PROTO', 'https')"
