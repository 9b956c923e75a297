"""Settings, read from environment variables (healthchecks style).

The embedded default needs nothing: SQLite under ``var/``, files under
``var/media``, and Celery tasks run in-process. Production sets
``DATABASE_URL`` (PostgreSQL), ``CELERY_BROKER_URL`` (Redis) and the storage.
"""

import os
from datetime import timedelta
from pathlib import Path
from urllib.parse import unquote, urlparse

from django.core.exceptions import ImproperlyConfigured

BASE_DIR = Path(__file__).resolve().parent.parent


def envbool(name, default):
    value = os.environ.get(name)
    if value is None:
        return default
    if value.lower() in ("1", "true", "yes", "on"):
        return True
    if value.lower() in ("0", "false", "no", "off", ""):
        return False
    raise ImproperlyConfigured(f"{name}={value!r} is not a boolean (use true or false)")


def envint(name, default):
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except ValueError:
        raise ImproperlyConfigured(f"{name}={value!r} is not an integer") from None


def database_from_url(url, name="DATABASE_URL"):
    """A Django DATABASES entry from ``sqlite:///path`` or ``postgres://user:pass@host:port/db``."""
    parsed = urlparse(url)
    if parsed.scheme == "sqlite":
        path = unquote(parsed.path)
        if parsed.netloc or not path:
            raise ImproperlyConfigured(f"{name}={url!r}: use sqlite:///relative/path or sqlite:////absolute/path")
        path = path[1:]  # sqlite:///rel/path -> rel/path, sqlite:////abs/path -> /abs/path
        file = Path(path) if Path(path).is_absolute() else BASE_DIR / path
        # Waits for another thread's write instead of failing at once ("database is locked"), and takes the
        # write lock when a transaction begins: a read-then-write transaction cannot deadlock with another.
        return {"ENGINE": "django.db.backends.sqlite3", "NAME": str(file),
                "OPTIONS": {"timeout": envint("SQLITE_TIMEOUT", 30), "transaction_mode": "IMMEDIATE"}}
    if parsed.scheme in ("postgres", "postgresql", "pgsql"):
        dbname = unquote(parsed.path.lstrip("/"))
        if not dbname:
            raise ImproperlyConfigured(f"{name}={url!r}: the database name is missing")
        return {
            "ENGINE": "django.db.backends.postgresql",
            "NAME": dbname,
            "USER": unquote(parsed.username or ""),
            "PASSWORD": unquote(parsed.password or ""),
            "HOST": parsed.hostname or "",
            "PORT": str(parsed.port or ""),
            "CONN_MAX_AGE": envint("DB_CONN_MAX_AGE", 60),
            # a kept connection is checked before a request's first query: after a database restart it is
            # dead, and the request reconnects instead of failing
            "CONN_HEALTH_CHECKS": True,
        }
    raise ImproperlyConfigured(f"{name}={url!r}: unsupported scheme {parsed.scheme!r} (use sqlite or postgres)")


DEVELOPMENT_SECRET_KEY = "insecure-development-key-do-not-use-in-production"


def check_secret_key(key):
    """Refuse a key that could be guessed (Django's own --deploy criteria, and the development default)."""
    if not key:
        problem = "is not set"
    elif key == DEVELOPMENT_SECRET_KEY or key.startswith("django-insecure"):
        problem = "is a development key"
    elif len(key) < 50 or len(set(key)) < 5:
        problem = "is too weak (use 50 characters or more, at least 5 different ones)"
    else:
        return key
    raise ImproperlyConfigured(f"SECRET_KEY {problem}; DEBUG is off, so set a random one, e.g. "
                               "python -c 'import secrets; print(secrets.token_urlsafe(50))'")


# Off unless asked for: `make demo` and the tests (pytest-env, pyproject.toml) set DEBUG=true.
DEBUG = envbool("DEBUG", False)
SECRET_KEY = os.environ.get("SECRET_KEY", "")
if DEBUG:
    SECRET_KEY = SECRET_KEY or DEVELOPMENT_SECRET_KEY
else:
    check_secret_key(SECRET_KEY)
ALLOWED_HOSTS = [h for h in os.environ.get("ALLOWED_HOSTS", "localhost,127.0.0.1,testserver").split(",") if h]

VAR_DIR = Path(os.environ.get("TORSOSCAN_VAR", BASE_DIR / "var"))
VAR_DIR.mkdir(parents=True, exist_ok=True)

INSTALLED_APPS = [
    "django.contrib.admin",
    "django.contrib.auth",
    "django.contrib.contenttypes",
    "django.contrib.sessions",
    "django.contrib.messages",
    "django.contrib.staticfiles",
    "django_celery_beat",
    "axes",  # login throttling and lockout (below)
    "ninja",  # /api/docs from its bundled static files (no CDN, no inline script)
    "clinic",
]

MIDDLEWARE = [
    "django.middleware.security.SecurityMiddleware",
    "whitenoise.middleware.WhiteNoiseMiddleware",
    "clinic.middleware.SecurityHeadersMiddleware",
    "django.contrib.sessions.middleware.SessionMiddleware",
    "django.middleware.common.CommonMiddleware",
    "django.middleware.csrf.CsrfViewMiddleware",
    "django.contrib.auth.middleware.AuthenticationMiddleware",
    "clinic.middleware.IdleSessionMiddleware",  # the idle timeout, without a write per request
    "clinic.audit.AuditMiddleware",  # who viewed or changed which patient's data (needs request.user)
    "django.contrib.messages.middleware.MessageMiddleware",
    "django.middleware.clickjacking.XFrameOptionsMiddleware",
    "axes.middleware.AxesMiddleware",  # last: turns a locked-out sign-in into the lockout page
]

# Sign-ins (the pages and the admin; the rig's bearer keys are not a login) are throttled per user name:
# after LOGIN_FAILURE_LIMIT failures the account is locked for LOGIN_COOLOFF_MINUTES, whatever the address.
# Not per address: a clinic's workstations share one address behind its NAT (and behind a proxy every client
# has the proxy's), so a few typos would lock the whole clinic out; hence axes.W006 is silenced below.
AUTHENTICATION_BACKENDS = ["axes.backends.AxesStandaloneBackend", "django.contrib.auth.backends.ModelBackend"]
AXES_FAILURE_LIMIT = envint("LOGIN_FAILURE_LIMIT", 5)
AXES_COOLOFF_TIME = timedelta(minutes=envint("LOGIN_COOLOFF_MINUTES", 15))
AXES_LOCKOUT_PARAMETERS = ["username"]
SILENCED_SYSTEM_CHECKS = ["axes.W006"]
AXES_RESET_ON_SUCCESS = True
AXES_LOCKOUT_TEMPLATE = "registration/locked_out.html"

# HTTPS in production (each on when DEBUG is off, each can be turned off, e.g. behind a proxy that already
# redirects). Behind a proxy that terminates TLS, SECURE_PROXY_SSL_HEADER names the header it sets
# (X-Forwarded-Proto: https); set it only there, since a client could send that header itself.
SECURE_SSL_REDIRECT = envbool("SECURE_SSL_REDIRECT", not DEBUG)
SESSION_COOKIE_SECURE = envbool("SESSION_COOKIE_SECURE", not DEBUG)
CSRF_COOKIE_SECURE = envbool("CSRF_COOKIE_SECURE", not DEBUG)
SECURE_HSTS_SECONDS = envint("SECURE_HSTS_SECONDS", 0 if DEBUG else 365 * 24 * 3600)
SECURE_HSTS_INCLUDE_SUBDOMAINS = envbool("SECURE_HSTS_INCLUDE_SUBDOMAINS", not DEBUG)
SECURE_HSTS_PRELOAD = envbool("SECURE_HSTS_PRELOAD", not DEBUG)
if os.environ.get("SECURE_PROXY_SSL_HEADER"):
    SECURE_PROXY_SSL_HEADER = ("HTTP_" + os.environ["SECURE_PROXY_SSL_HEADER"].upper().replace("-", "_"), "https")
SECURE_CONTENT_TYPE_NOSNIFF = True
SECURE_REFERRER_POLICY = "same-origin"
X_FRAME_OPTIONS = "DENY"
# Shared clinic workstations: a session ends after SESSION_IDLE_MINUTES without a request, and with the browser.
SESSION_COOKIE_AGE = envint("SESSION_IDLE_MINUTES", 15) * 60
# the expiry moves forward at most once a minute (clinic.middleware.IdleSessionMiddleware), not by a write per
# request: the idle timeout is exact to within SESSION_REFRESH_SECONDS
SESSION_SAVE_EVERY_REQUEST = False
SESSION_REFRESH_SECONDS = envint("SESSION_REFRESH_SECONDS", 60)
SESSION_EXPIRE_AT_BROWSER_CLOSE = True

ROOT_URLCONF = "clinic.urls"
WSGI_APPLICATION = "clinic.wsgi.application"

TEMPLATES = [{
    "BACKEND": "django.template.backends.django.DjangoTemplates",
    "DIRS": [BASE_DIR / "templates"],
    "APP_DIRS": True,
    "OPTIONS": {"context_processors": [
        "django.template.context_processors.request",
        "django.contrib.auth.context_processors.auth",
        "django.contrib.messages.context_processors.messages",
    ]},
}]

DATABASES = {"default": database_from_url(os.environ.get("DATABASE_URL", "sqlite:///var/clinic.sqlite3"))}
DEFAULT_AUTO_FIELD = "django.db.models.BigAutoField"


def cache_from_url(url, name="CACHE_URL"):
    """A Django CACHES entry: ``redis://host:port/db`` (shared by every process of the service: a drawn report
    or chart serves all of them), or empty for each process's own memory (the embedded default)."""
    if not url:
        return {"BACKEND": "django.core.cache.backends.locmem.LocMemCache"}
    scheme = urlparse(url).scheme
    if scheme in ("redis", "rediss"):
        return {"BACKEND": "django.core.cache.backends.redis.RedisCache", "LOCATION": url,
                "TIMEOUT": envint("CACHE_SECONDS", 86400)}
    raise ImproperlyConfigured(f"{name}={url!r}: unsupported scheme {scheme!r} (use redis, or leave it empty)")


CACHES = {"default": cache_from_url(os.environ.get("CACHE_URL", ""))}

LANGUAGE_CODE = "en-us"
TIME_ZONE = os.environ.get("TIME_ZONE", "UTC")
USE_TZ = True

STATIC_URL = "static/"
STATIC_ROOT = Path(os.environ.get("STATIC_ROOT", VAR_DIR / "static"))
STATIC_ROOT.mkdir(parents=True, exist_ok=True)
# WhiteNoise serves the apps' static files (the pages' stylesheet, the admin's, /api/docs') straight from their
# folders: no collectstatic step, and the same in production as under runserver.
WHITENOISE_USE_FINDERS = True
MEDIA_ROOT = Path(os.environ.get("MEDIA_ROOT", VAR_DIR / "media"))
MEDIA_URL = "media/"

# Files through Django's storage API: the local file system by default, an
# S3-compatible store (django-storages) when STORAGE_BACKEND names it.
def storage_options(backend):
    """OPTIONS of the default storage: a folder, or an S3-compatible bucket from S3_* variables."""
    if backend == "django.core.files.storage.FileSystemStorage":
        return {"location": str(MEDIA_ROOT)}
    if backend.startswith("storages.backends.s3"):
        bucket = os.environ.get("S3_BUCKET", "")
        if not bucket:
            raise ImproperlyConfigured(f"STORAGE_BACKEND={backend} needs S3_BUCKET")
        options = {"bucket_name": bucket, "default_acl": None, "file_overwrite": False}
        for var, key in (("S3_ENDPOINT_URL", "endpoint_url"), ("S3_REGION", "region_name"),
                         ("S3_ACCESS_KEY_ID", "access_key"), ("S3_SECRET_ACCESS_KEY", "secret_key"),
                         ("S3_LOCATION", "location")):
            if os.environ.get(var):
                options[key] = os.environ[var]
        return options
    return {}


STORAGE_BACKEND = os.environ.get("STORAGE_BACKEND", "django.core.files.storage.FileSystemStorage")
STORAGES = {
    "default": {"BACKEND": STORAGE_BACKEND, "OPTIONS": storage_options(STORAGE_BACKEND)},
    "staticfiles": {"BACKEND": "django.contrib.staticfiles.storage.StaticFilesStorage"},
}

# Uploads: images are streamed to a temporary file in chunks, never held whole
# in memory (the API reads the raw body itself, so DATA_UPLOAD_MAX_MEMORY_SIZE
# and DATA_UPLOAD_MAX_NUMBER_FILES never see them; they stay at Django's
# defaults for forms).
FILE_UPLOAD_TEMP_DIR = str(VAR_DIR / "tmp")
Path(FILE_UPLOAD_TEMP_DIR).mkdir(parents=True, exist_ok=True)
MAX_IMAGE_BYTES = envint("MAX_IMAGE_BYTES", 200 * 1024 * 1024)
MAX_BUNDLE_BYTES = envint("MAX_BUNDLE_BYTES", 2 * 1024 * 1024 * 1024)
# a bundle's capture.json is read into memory: a few KiB in practice (20 images), 1 MiB at most
MAX_MANIFEST_BYTES = envint("MAX_MANIFEST_BYTES", 1024 * 1024)
# where workers unpack captures for the engine (local to each worker)
WORK_DIR = os.environ.get("WORK_DIR", str(VAR_DIR / "work"))

LOGIN_URL = "login"
LOGIN_REDIRECT_URL = "patients"
LOGOUT_REDIRECT_URL = "login"

# Celery: without a broker, tasks run in-process (the embedded default).
CELERY_BROKER_URL = os.environ.get("CELERY_BROKER_URL", "")
CELERY_RESULT_BACKEND = os.environ.get("CELERY_RESULT_BACKEND", "") or None
CELERY_TASK_ALWAYS_EAGER = not CELERY_BROKER_URL
CELERY_TASK_EAGER_PROPAGATES = True
CELERY_TASK_ACKS_LATE = True
CELERY_TASK_REJECT_ON_WORKER_LOST = True
CELERY_WORKER_PREFETCH_MULTIPLIER = 1
CELERY_TASK_SOFT_TIME_LIMIT = envint("CELERY_TASK_SOFT_TIME_LIMIT", 3600)
CELERY_TASK_TIME_LIMIT = envint("CELERY_TASK_TIME_LIMIT", 3900)
# a task not acknowledged within this time is redelivered: above the hard limit. A Redis that does not answer
# is given up on (2 s to connect, 5 s for a reply; a worker's polls wait 1 s), so it cannot hold a request.
CELERY_BROKER_TRANSPORT_OPTIONS = {"visibility_timeout": CELERY_TASK_TIME_LIMIT + 600,
                                   "socket_connect_timeout": 2, "socket_timeout": 5}
CELERY_TASK_DEFAULT_QUEUE = os.environ.get("CELERY_QUEUE", "torsoscan")
# A broker that is down must not hold a request: publishing gives up after about a second (the job's row is the
# record of work; the sweeper below sends it when the broker is back). The connection timeout is AMQP's.
CELERY_BROKER_CONNECTION_TIMEOUT = 2
CELERY_TASK_PUBLISH_RETRY_POLICY = {"max_retries": 2, "interval_start": 0, "interval_step": 0.5, "interval_max": 0.5}
CELERY_TASK_SERIALIZER = "json"
CELERY_ACCEPT_CONTENT = ["json"]

# Jobs survive the broker and their workers: a step's claim holds a lease its
# worker renews (every quarter of it); a queued step not taken for
# JOB_REDISPATCH_SECONDS, or a claim whose lease lapsed, is sent again by the
# sweeper, which beat runs every JOB_SWEEP_SECONDS. A worker that dies is thus
# replaced within JOB_LEASE_SECONDS + JOB_SWEEP_SECONDS (once a worker slot is free).
JOB_LEASE_SECONDS = envint("JOB_LEASE_SECONDS", 120)
JOB_REDISPATCH_SECONDS = envint("JOB_REDISPATCH_SECONDS", 60)
# a step whose worker stopped holding it this many times (killed each time: out of memory on this capture,
# say) is not sent again: its job (or arm) fails saying so, and its capture stays for a re-run
JOB_MAX_TAKEOVERS = envint("JOB_MAX_TAKEOVERS", 3)
JOB_SWEEP_SECONDS = envint("JOB_SWEEP_SECONDS", 30)

# Scheduled work (Celery beat with django-celery-beat's database scheduler):
# rigs due for recalibration are flagged; stalled jobs are sent again; stored files are checked against rows.
CELERY_BEAT_SCHEDULER = "django_celery_beat.schedulers:DatabaseScheduler"
CELERY_BEAT_SCHEDULE = {
    "flag-rigs-for-recalibration": {
        "task": "clinic.tasks.flag_rigs_for_recalibration",
        "schedule": envint("RECALIBRATION_CHECK_SECONDS", 3600),
    },
    "redispatch-stalled-jobs": {
        "task": "clinic.tasks.redispatch_stalled",
        "schedule": JOB_SWEEP_SECONDS,
        # a sweep still waiting behind busy workers when the next one is due is dropped, not piled up
        "options": {"expire_seconds": JOB_SWEEP_SECONDS},
    },
    # stored files no row references, rows whose file is missing: logged (manage.py check_files to act)
    "check-stored-files": {
        "task": "clinic.tasks.check_files",
        "schedule": envint("FILE_CHECK_SECONDS", 24 * 3600),
    },
}

# Logs go to the console (the container's log) through the root logger: the app's loggers at LOG_LEVEL (INFO
# by default), and every unexpected error of a request with its traceback (django.request logs a page's 500 at
# ERROR; the API logs its own, under the id its answer gives). A Celery worker puts its own handler on the root.
LOG_LEVEL = os.environ.get("LOG_LEVEL", "INFO").upper()
if LOG_LEVEL not in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"):
    raise ImproperlyConfigured(f"LOG_LEVEL={LOG_LEVEL!r}: use DEBUG, INFO, WARNING, ERROR or CRITICAL")
LOGGING = {
    "version": 1,
    "disable_existing_loggers": False,
    "formatters": {"plain": {"format": "%(asctime)s %(levelname)s %(name)s: %(message)s"}},
    "handlers": {"console": {"class": "logging.StreamHandler", "formatter": "plain"}},
    "root": {"handlers": ["console"], "level": "WARNING"},
    "loggers": {
        # Django's own console handler (DEBUG only) and mail to ADMINS are replaced by the root's
        "django": {"handlers": [], "level": "INFO", "propagate": True},
        "django.request": {"level": "ERROR", "propagate": True},
        **{name: {"level": LOG_LEVEL, "propagate": True} for name in ("clinic", "recon_engine", "analysis")},
    },
}
