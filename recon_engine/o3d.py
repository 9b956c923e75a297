"""Open3D, imported without its Plotly helpers: ``from recon_engine.o3d import o3d``.

``import open3d`` (0.20) imports ``open3d.visualization.draw_plotly``, which
imports Dash and Plotly: about 1 s of one core and 40 MB in every process
that imports Open3D (the simulator's render workers, the Celery worker's
processes, every command), for three plotting functions the project never
calls. Here a stand-in takes that module's place in ``sys.modules`` while
Open3D is imported; each of its functions imports the real module on its
first call, so nothing is lost. If an Open3D release expects more of that
module than the stand-in has, Open3D is imported the ordinary way.
"""

from __future__ import annotations

import importlib
import sys
import types

PLOTLY_MODULE = "open3d.visualization.draw_plotly"
PLOTLY_FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _stand_in() -> types.ModuleType:
    """A module with ``PLOTLY_FUNCTIONS`` that import the real one when called."""
    stand_in = types.ModuleType(PLOTLY_MODULE)
    stand_in.__doc__ = "Stand-in for Open3D's Plotly helpers (recon_engine.o3d): the real module loads on first call."

    def real():
        if sys.modules.get(PLOTLY_MODULE) is stand_in:
            del sys.modules[PLOTLY_MODULE]
        return importlib.import_module(PLOTLY_MODULE)

    def forward(name):
        def call(*args, **kwargs):
            return getattr(real(), name)(*args, **kwargs)
        call.__name__ = call.__qualname__ = name
        return call

    for name in PLOTLY_FUNCTIONS:
        setattr(stand_in, name, forward(name))

    def other(name):
        """Anything else asked of the stand-in (the module's other helpers) comes from the real module; not the
        import machinery's own questions (``__path__``, ``__spec__``, ...), which must not load it."""
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(real(), name)

    stand_in.__getattr__ = other
    return stand_in


def _import_open3d() -> types.ModuleType:
    if "open3d" in sys.modules:  # imported already (by the caller's own code): nothing left to save
        return sys.modules["open3d"]
    stand_in = _stand_in()
    sys.modules[PLOTLY_MODULE] = stand_in
    try:
        return importlib.import_module("open3d")
    except ImportError:
        # a release whose visualization package wants more of draw_plotly: import it whole
        for name in [m for m in sys.modules if m == "open3d" or m.startswith("open3d.")]:
            del sys.modules[name]
        return importlib.import_module("open3d")
    finally:
        if sys.modules.get(PLOTLY_MODULE) is stand_in and "open3d" not in sys.modules:
            del sys.modules[PLOTLY_MODULE]


o3d = _import_open3d()
