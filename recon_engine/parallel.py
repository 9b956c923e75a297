"""How many threads or processes the engine's stages use."""

from __future__ import annotations

import os


def cores(requested: int = 0) -> int:
    """``requested`` when positive, else one per core of this machine."""
    return requested if requested > 0 else (os.cpu_count() or 1)
