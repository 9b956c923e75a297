"""Work done once per request key (a form's one-time token, an API client's Idempotency-Key).

The first request claims the key, does the work and stores its outcome under it; a repeat waits for that
outcome instead of doing the work again. Kept in the cache, which production shares between the service's
processes (``CACHE_URL``; the embedded default is one process).
"""

import time

from django.core.cache import cache

PENDING = ""  # claimed: the first request is still working


def claim(key: str, seconds: int) -> bool:
    """Whether this request claimed ``key`` for ``seconds`` (it then does the work and calls :func:`settle` or
    :func:`release`); False if another request holds it."""
    return cache.add(key, PENDING, seconds)


def first_outcome(key: str, wait_s: float = 10.0):
    """What the request holding ``key`` stored, waiting up to ``wait_s`` (s) while it works: its outcome (truthy),
    None (it released the key, or the cache forgot it: the work is to be done again), or :data:`PENDING` (still
    working when the wait ended)."""
    deadline = time.monotonic() + wait_s
    while True:
        value = cache.get(key)
        if value != PENDING or time.monotonic() >= deadline:
            return value
        time.sleep(0.25)


def settle(key: str, outcome, seconds: int) -> None:
    cache.set(key, outcome, seconds)


def release(key: str) -> None:
    cache.delete(key)
