"""Benchmark: simulate a scenario and measure time, peak memory and faithfulness.

    .venv/bin/python benchmarks/bench_simulate.py --preset paper --out bench-out/paper

Prints a Markdown summary (for docs/benchmarks.md) and writes it with the raw
figures to ``OUT/../bench_simulate_<preset>.json``.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from provenance import provenance  # noqa: E402
from recon_engine.simulator.checks import marker_corner_errors, neighbour_ncc  # noqa: E402
from recon_engine.simulator.config import PRESETS, preset  # noqa: E402
from recon_engine.simulator.scenario import simulate  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper", choices=list(PRESETS))
    ap.add_argument("--out", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--reuse", action="store_true",
                    help="keep an existing scenario in OUT and only re-run the checks (timings from the last run)")
    args = ap.parse_args()
    run = provenance(__file__)
    out = Path(args.out or f"bench-out/{args.preset}")
    cfg = preset(args.preset, seed=args.seed)
    previous = out.parent / f"bench_simulate_{args.preset}.json"
    if args.reuse and (out / "truth" / "scenario.json").exists() and previous.exists():
        summary = json.loads((out / "truth" / "scenario.json").read_text())["summary"]
        last = json.loads(previous.read_text())
        wall = last["wall_s"]
        peak_self, peak_children = last["peak_rss_mib"]["main"], last["peak_rss_mib"]["largest_worker"]
    else:
        t0 = time.perf_counter()
        summary = simulate(out, cfg, force=True, workers=args.workers)
        wall = time.perf_counter() - t0
        peak_self = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        peak_children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    n_images = len(summary["captures"]) * 20

    t1 = time.perf_counter()
    corners = marker_corner_errors(out)
    ncc = {name: neighbour_ncc(out, name) for name, _ in cfg.captures}
    t_checks = time.perf_counter() - t1
    medians = [p["median"] for pairs in ncc.values() for p in pairs.values()]
    result = {
        **run, "preset": args.preset, "seed": args.seed,
        "images": n_images, "image_size": [cfg.camera.width, cfg.camera.height],
        "wall_s": round(wall, 1), "per_capture_s": summary["timings_s"],
        "peak_rss_mib": {"main": round(peak_self), "largest_worker": round(peak_children)},
        "marker_corner_error_px": {
            "edge_fit": {"n": int(len(corners["edge_fit"])), "median": float(np.median(corners["edge_fit"])),
                         "p95": float(np.percentile(corners["edge_fit"], 95))},
            "opencv_subpix": {"n": int(len(corners["opencv_subpix"])),
                              "median": float(np.median(corners["opencv_subpix"])),
                              "p95": float(np.percentile(corners["opencv_subpix"], 95))},
        },
        "neighbour_ncc": {"median_of_pair_medians": float(np.median(medians)), "min_pair_median": float(np.min(medians)),
                          "pairs": ncc},
        "checks_s": round(t_checks, 1),
    }
    dest = out.parent / f"bench_simulate_{args.preset}.json"
    dest.write_text(json.dumps(result, indent=2))
    c = result["marker_corner_error_px"]
    print(f"""
### Simulator, preset `{args.preset}` (commit {run['commit']})

Command: `{result['command']}`
Machine: {result['machine']}

| figure | value |
|---|---|
| images rendered | {n_images} of {cfg.camera.width} x {cfg.camera.height} px ({len(summary['captures'])} captures) |
| wall time, whole scenario | {wall:.0f} s ({wall / n_images:.1f} s per image) |
| per capture | {', '.join(f'{k}: {v:.0f} s' for k, v in summary['timings_s'].items() if k != 'total')} |
| peak memory | main process {peak_self:.0f} MiB, largest render worker {peak_children:.0f} MiB |
| marker corners vs truth, edge fit (ours) | median {c['edge_fit']['median']:.3f} px, 95th pct {c['edge_fit']['p95']:.3f} px, n = {c['edge_fit']['n']} |
| marker corners vs truth, OpenCV cornerSubPix | median {c['opencv_subpix']['median']:.3f} px, 95th pct {c['opencv_subpix']['p95']:.3f} px |
| NCC of neighbours' patches at true torso points | median of pair medians {result['neighbour_ncc']['median_of_pair_medians']:.3f}, lowest pair {result['neighbour_ncc']['min_pair_median']:.3f} |
""")
    print(f"raw figures: {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
