"""Open3D's import leaves out its Plotly helpers (Dash and Plotly: about 1 s and 40 MB per process) until one is
called (recon_engine/o3d.py)."""

import subprocess
import sys

PROBE = """
import sys
from recon_engine.o3d import o3d
import recon_engine.registration, recon_engine.simulator.render
print(sorted(m for m in ("dash", "plotly") if m in sys.modules))
import importlib
print(callable(importlib.import_module("open3d.visualization.draw_plotly").get_point_object))
import numpy as np
cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random((20, 3))))
figure = o3d.visualization.get_plotly_fig([cloud])
print(type(figure).__module__.split(".")[0], len(figure.data))
"""


def test_the_engine_imports_open3d_without_dash_and_the_plotly_helpers_still_work():
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    before, other, figure = r.stdout.strip().splitlines()
    assert before == "[]", f"Dash or Plotly imported with Open3D: {before}"
    assert other == "True"  # the module's other helpers come from the real module
    assert figure == "plotly 1"  # and the stand-in's functions forward to Open3D's own
