"""Reaching the real services the service tests use.

When PostgreSQL or Redis is unreachable: in CI (``CI=true``) that is a
failure, elsewhere a skip that says so.
"""

import os
import socket

import pytest

REDIS_URL = os.environ.get("TEST_REDIS_URL", "redis://127.0.0.1:6379/15")
POSTGRES = {"host": "127.0.0.1", "port": 5432, "user": "postgres"}


def _unreachable(what: str):
    message = f"{what} is unreachable"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"{message} (CI requires it)")
    pytest.skip(f"{message}; start it to run this test")


def _port_open(host, port) -> bool:
    try:
        with socket.create_connection((host, port), timeout=2):
            return True
    except OSError:
        return False


def require_redis() -> str:
    if not _port_open("127.0.0.1", 6379):
        _unreachable("Redis at 127.0.0.1:6379")
    return REDIS_URL


def require_postgres(dbname: str = "torsoscan_test") -> str:
    """A PostgreSQL database for the test (created when missing); its DATABASE_URL."""
    if not _port_open(POSTGRES["host"], POSTGRES["port"]):
        _unreachable("PostgreSQL at 127.0.0.1:5432")
    import psycopg

    try:
        with psycopg.connect(dbname="postgres", autocommit=True, **POSTGRES) as conn:
            exists = conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (dbname,)).fetchone()
            if not exists:
                conn.execute(f'CREATE DATABASE "{dbname}"')
    except psycopg.OperationalError as exc:
        _unreachable(f"PostgreSQL ({exc})")
    return f"postgres://postgres@127.0.0.1:5432/{dbname}"
