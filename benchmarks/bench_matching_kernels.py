"""Benchmark: the matcher's compiled kernels against the numpy code they replaced, on a synthetic pair.

    .venv/bin/python benchmarks/bench_matching_kernels.py [--reference 43bb649]

A paper-scale pair (3000 × 2000 px, a blurred random pattern; the right
image the left one stretched by 0.8 along the rows, shifted and with noise)
and 20 000 points. Timed on one thread (CPU time of this process, so that
other load on the machine counts less):

- the correlation search (``matching.ncc_search``): stage 2's shape (7-px
  window, ±6 columns, ±2 rows) and growing's (11 px, ±3, ±2), with the
  points in Harris order (scattered) and row by row (as the matcher now
  passes them);
- least-squares matching (``matching.least_squares_refine``, 9-px window,
  with and without the template's blur, stretch 0.85 to start), from starts
  0.3 px off the truth, row by row in blocks of 8000 points.

With ``--reference`` the same calls are made with ``recon_engine/matching.py``
as it was at that commit (read with ``git show``; 43bb649 is the last numpy
one), and the results compared point by point. Writes
``bench-out/bench_matching_kernels.json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from recon_engine import matching  # noqa: E402

from provenance import provenance  # noqa: E402


def reference_module(commit: str):
    """``recon_engine/matching.py`` at ``commit`` as a module (its relative imports made absolute)."""
    text = subprocess.run(["git", "show", f"{commit}:recon_engine/matching.py"], cwd=ROOT, check=True,
                          capture_output=True, text=True).stdout
    text = text.replace("from .", "from recon_engine.")
    path = Path(tempfile.mkdtemp()) / f"matching_{commit}.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def synthetic_pair(seed: int = 1):
    rng = np.random.default_rng(seed)
    h, w = 2000, 3000
    left = cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.float32), (0, 0), 1.5)
    # right column xr shows left column 1500 + (xr - 1500) / 0.8 + 20.3, and row yr shows left row yr + 0.2
    xs = np.arange(w, dtype=np.float32)
    mapx = np.tile(1500 + (xs - 1500) / 0.8 + 20.3, (h, 1)).astype(np.float32)
    mapy = np.tile(np.arange(h, dtype=np.float32)[:, None] + 0.2, (1, w))
    right = cv2.remap(left, mapx, mapy, cv2.INTER_CUBIC) + rng.normal(0, 1, (h, w)).astype(np.float32)
    n = 20_000
    xy = np.column_stack([rng.uniform(400, 2600, n), rng.uniform(30, h - 30, n)])
    true_right = np.column_stack([1500 + 0.8 * (xy[:, 0] - 20.3 - 1500), xy[:, 1] - 0.2])
    start = true_right + rng.normal(0, 0.3, (n, 2))
    return left, right, xy, true_right, start


def timed(fn, *args, repeats: int = 3):
    """(result of the last call ``fn(*args)``, least CPU seconds of ``repeats`` calls)."""
    best, out = np.inf, None
    for _ in range(repeats):
        t = time.process_time()
        out = fn(*args)
        best = min(best, time.process_time() - t)
    return out, best


def search_all(module, left, right, xy, x_centre, order, radius, window):
    """``module.ncc_search`` of every point, taken in ``order`` in blocks of 2000 (as the numpy code ran them, in
    cache-sized blocks); the right points in the points' own order."""
    parts = [module.ncc_search(left, right, xy[order[s:s + 2000]], x_centre[order[s:s + 2000]], radius, 2, window,
                               scale=0.8) for s in range(0, len(xy), 2000)]
    return np.concatenate([p["xy"] for p in parts])[np.argsort(order)]


def refine_all(module, left, right, xy, start, rows, antialias_px):
    """``module.least_squares_refine`` of every point, row by row in blocks of 8000 (as the matcher passes them:
    ``MatchingConfig.chunk`` × 2); the results in the points' own order."""
    parts = [module.least_squares_refine(left, right, xy[rows[s:s + 8000]], start[rows[s:s + 8000]], window=9,
                                         initial_scale=0.85, antialias_px=antialias_px, _again=False)
             for s in range(0, len(xy), 8000)]
    return {k: np.concatenate([p[k] for p in parts])[np.argsort(rows)] for k in parts[0]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", default=None, help="a commit whose matching.py to compare with (e.g. 43bb649)")
    args = ap.parse_args()
    run = provenance(__file__)
    left, right, xy, true_right, start = synthetic_pair()
    n = len(xy)
    rows = matching.along_rows(xy)
    modules = {"kernels": matching}
    if args.reference:
        modules[f"numpy ({args.reference})"] = reference_module(args.reference)
    matching.ncc_search(left, right, xy[:4], true_right[:4, 0], 2, 1, 7)  # compiled or loaded outside the timing
    matching.least_squares_refine(left, right, xy[:4], start[:4], window=9)
    out = {**run,
           "points": n, "us_per_point": {}, "agreement": {}}
    results = {}
    searches = {"ncc 7 px, ±6 × ±2": (6, 7), "ncc 11 px, ±3 × ±2": (3, 11)}
    for name, module in modules.items():
        times = {}
        for label, (radius, window) in searches.items():
            for order_name, order in (("scattered", np.arange(n)), ("row by row", rows)):
                r, t = timed(search_all, module, left, right, xy, true_right[:, 0], order, radius, window)
                times[f"{label}, {order_name}"] = t / n * 1e6
                results[(name, label, order_name)] = r
        for label, antialias in (("lsm 9 px", 0.0), ("lsm 9 px, blurred template", 0.7)):
            r, t = timed(refine_all, module, left, right, xy, start, rows, antialias, repeats=2)
            times[label] = t / n * 1e6
            results[(name, label)] = r
        out["us_per_point"][name] = times
        print(name, {k: round(v, 2) for k, v in times.items()}, flush=True)
    if args.reference:
        ref = f"numpy ({args.reference})"
        agree = {}
        for label in searches:
            a, b = results[("kernels", label, "row by row")], results[(ref, label, "row by row")]
            d = np.abs(a - b).max(axis=1)
            agree[label] = {"median_px": float(np.median(d)), "p99_px": float(np.percentile(d, 99)),
                            "over_half_px": int((d > 0.5).sum())}
        for label in ("lsm 9 px", "lsm 9 px, blurred template"):
            a, b = results[("kernels", label)], results[(ref, label)]
            both = a["converged"] & b["converged"]
            d = np.abs(a["xy"][both] - b["xy"][both]).max(axis=1)
            agree[label] = {"converged_same": float(np.mean(a["converged"] == b["converged"])),
                            "median_px": float(np.median(d)), "max_px": float(d.max()),
                            "error_to_truth_px": {k: float(np.median(np.abs(r["xy"][both] - true_right[both])))
                                                  for k, r in (("kernels", a), (ref, b))}}
        out["agreement"] = agree
        print(json.dumps(agree, indent=1))
        out["speed_up"] = {k: out["us_per_point"][ref][k] / v for k, v in out["us_per_point"]["kernels"].items()}
        print("speed-up (reference ÷ kernels):", {k: round(v, 2) for k, v in out["speed_up"].items()})
    dest = ROOT / "bench-out" / "bench_matching_kernels.json"
    dest.parent.mkdir(exist_ok=True)
    dest.write_text(json.dumps(out, indent=2))
    print(f"raw figures: {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
