import pytest
from django.core.exceptions import ImproperlyConfigured

from clinic.settings import BASE_DIR, database_from_url, envbool, envint


def test_it_reads_a_relative_sqlite_url():
    db = database_from_url("sqlite:///var/x.sqlite3")
    assert db["ENGINE"].endswith("sqlite3") and db["NAME"] == str(BASE_DIR / "var" / "x.sqlite3")


def test_it_reads_an_absolute_sqlite_url():
    assert database_from_url("sqlite:////tmp/x.sqlite3")["NAME"] == "/tmp/x.sqlite3"


def test_it_reads_a_postgres_url():
    db = database_from_url("postgres://alice:s%40cret@db.example:6543/clinic")
    assert db["ENGINE"].endswith("postgresql")
    assert (db["NAME"], db["USER"], db["PASSWORD"], db["HOST"], db["PORT"]) == ("clinic", "alice", "s@cret", "db.example", "6543")


def test_it_rejects_an_unknown_scheme_naming_the_variable():
    with pytest.raises(ImproperlyConfigured, match="DATABASE_URL=.*mysql"):
        database_from_url("mysql://x/y")


def test_it_rejects_a_postgres_url_without_database():
    with pytest.raises(ImproperlyConfigured, match="database name"):
        database_from_url("postgres://u@h:5432/")


def test_it_rejects_bad_booleans_and_integers(monkeypatch):
    monkeypatch.setenv("X_FLAG", "maybe")
    with pytest.raises(ImproperlyConfigured, match="X_FLAG"):
        envbool("X_FLAG", False)
    monkeypatch.setenv("X_INT", "ten")
    with pytest.raises(ImproperlyConfigured, match="X_INT"):
        envint("X_INT", 1)


def test_it_reads_a_redis_cache_url_and_keeps_each_process_own_cache_without_one():
    from clinic.settings import cache_from_url

    assert cache_from_url("")["BACKEND"].endswith("LocMemCache")
    c = cache_from_url("redis://redis:6379/2")
    assert c["BACKEND"].endswith("RedisCache") and c["LOCATION"] == "redis://redis:6379/2"
    with pytest.raises(ImproperlyConfigured, match="CACHE_URL=.*memcached"):
        cache_from_url("memcached://x:11211")

