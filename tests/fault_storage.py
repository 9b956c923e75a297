"""The file system storage with faults a test arms by creating a file in TORSOSCAN_VAR (each fires once).

- ``fault-barrier``: the next two saves wait for each other before saving
  (two uploads of one image, both past every check, racing to store it);
- ``fault-terminate``: right after the next save, the database connection of
  the request is killed by PostgreSQL (``pg_terminate_backend``, as a
  restart or a network cut does), before the row names the file.
"""

import threading
from pathlib import Path

from django.conf import settings
from django.core.files.storage import FileSystemStorage

_barrier = threading.Barrier(2, timeout=20)
_lock = threading.Lock()
_barrier_saves = 0


def _take(fault: str) -> bool:
    marker = Path(settings.VAR_DIR) / f"fault-{fault}"
    try:
        marker.unlink()
        return True
    except FileNotFoundError:
        return False


class FaultStorage(FileSystemStorage):
    def _save(self, name, content):
        global _barrier_saves
        with _lock:
            if _barrier_saves == 0 and _take("barrier"):
                _barrier_saves = 2
            waits = _barrier_saves > 0
            _barrier_saves -= waits
        if waits:
            _barrier.wait()
        saved = super()._save(name, content)
        if _take("terminate"):
            import psycopg
            from django.db import connection

            pid = connection.connection.info.backend_pid
            with psycopg.connect(dbname=connection.settings_dict["NAME"], host="127.0.0.1", user="postgres",
                                 autocommit=True) as killer:
                killer.execute("SELECT pg_terminate_backend(%s)", (pid,))
        return saved
