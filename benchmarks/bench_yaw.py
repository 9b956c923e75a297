"""The patient frame's yaw: which part of the trunk it is read from (issue 27 §2, §4).

Every section's surface rotation is measured against the patient frame's posterior direction, so an error in
the frame's yaw (its turn about the vertical) enters every section's rotation, and a change of it between two
same-day scans enters every rotation's re-scan change. The analysis first takes the yaw from the whole torso's
mirror plane, then again from a band of the trunk (``analysis.indices.band_yaw_frame``). This script measures,
for each candidate band, on the same scans:

- the yaw's error against the simulated posture's (its posterior direction; the simulator rotates the trunk's
  sections about the spine relative to the pelvis, so the posture's yaw is the pelvis's), deg;
- how far it moves when the landmark its band rests on moves: VP by -6..+6 mm, SP by -12..+12 mm (what a
  landmark's same-day spread does to the frame), deg;
- its change between a body's baseline and same-day re-scan (each against its own posture), deg.

Bands (``b`` = ``IndicesConfig.yaw_band`` of the trunk's length L = VP - SP):

- ``pelvis``: SP ± b·L (the analysis's since 2026-12-04);
- ``ends``: the pelvis band and VP - b·L .. VP (before);
- ``shoulders``: VP - b·L .. VP;
- ``whole``: the whole torso's mirror plane (the first estimate).

Sources: true surfaces sampled as in ``bench_bodies.py`` (``--seed``, baseline and re-scan of each body,
the same draws as that script's), and/or the reconstructed torsos ``bench_rescans.py`` kept
(``--rendered bench-out/rescans-demo/demo --set tune``).

    .venv/bin/python benchmarks/bench_yaw.py --seed 100 --bodies 10 \\
        --rendered bench-out/rescans-demo/demo --set tune --json docs/results/bench_yaw_tune.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from analysis.config import IndicesConfig  # noqa: E402
from analysis.indices import band_yaw_frame, initial_frame  # noqa: E402
from analysis.torso import read_torso  # noqa: E402
from bench_bodies import draw_scans  # noqa: E402
from provenance import provenance  # noqa: E402

BANDS = ("pelvis", "ends", "shoulders", "whole")
VP_SHIFTS_MM = (-6.0, 0.0, 6.0)
SP_SHIFTS_MM = (-12.0, 0.0, 12.0)


def yaw_deg(posterior) -> float:
    """Heading (deg) of a posterior direction about +Z, from +Y towards +X (rig frame)."""
    return float(np.degrees(np.arctan2(posterior[0], posterior[1])))


def band_limits(name: str, z_sp: float, z_vp: float, b: float) -> list:
    L = z_vp - z_sp
    pelvis, shoulders = (z_sp - b * L, z_sp + b * L), (z_vp - b * L, z_vp)
    return {"pelvis": [pelvis], "ends": [pelvis, shoulders], "shoulders": [shoulders]}[name]


def measure_scan(torso, true_yaw: float, ic: IndicesConfig) -> dict:
    """Each band's yaw error (deg) at the found landmarks and under VP and SP moved."""
    start = initial_frame(torso, ic)
    z_sp, z_vp = start["auto"]["sacral_point"][2], start["auto"]["vertebra_prominens"][2]
    out = {"z_sp": float(z_sp), "z_vp": float(z_vp)}

    def err(name, dsp, dvp):
        if name == "whole":
            return yaw_deg(start["frame"].R[1]) - true_yaw
        f = band_yaw_frame(torso, start, band_limits(name, z_sp + dsp, z_vp + dvp, ic.yaw_band))
        return float("nan") if f is None else yaw_deg(f.R[1]) - true_yaw

    for name in BANDS:
        e0 = err(name, 0.0, 0.0)
        # the whole torso's plane rests on no landmark
        vp = [e0 if d == 0 else err(name, 0.0, d) for d in VP_SHIFTS_MM] if name != "whole" else [np.nan]
        sp = [e0 if d == 0 else err(name, d, 0.0) for d in SP_SHIFTS_MM] if name != "whole" else [np.nan]
        moved = lambda v: float(np.nanmax(v) - np.nanmin(v)) if np.isfinite(v).any() else float("nan")  # noqa: E731
        out[name] = {"error_deg": e0, "vp_moved_deg": moved(vp), "sp_moved_deg": moved(sp)}
    return out


def true_surface_scans(seed: int, n_bodies: int, n_points: int):
    """Baseline and same-day re-scan of each body, drawn exactly as bench_bodies.run_set draws them."""
    for b, _, name, s, t in draw_scans(seed, n_bodies, n_points):
        if name in ("baseline", "rescan"):  # the later visits are drawn only to keep the random stream
            yield b, name, t, yaw_deg(s["posture"].R @ np.array([0.0, 1.0, 0.0]))


def rendered_scans(root: Path, which: str):
    """The reconstructed baseline and re-scan of each kept body of a bench_rescans.py set."""
    for body_dir in sorted(root.glob(f"{which}-*")):
        body = int(body_dir.name.split("-")[-1])
        for name, capture in (("baseline", "visit0-a"), ("rescan", "visit0-b")):
            torso_dir = body_dir / "torsos" / capture
            if not (torso_dir / "torso.ply").exists():
                continue
            if json.loads((torso_dir / "report.json").read_text())["status"] == "failed":
                continue
            truth = json.loads((body_dir / "scenario" / "truth" / capture / "truth.json").read_text())
            R = np.asarray(truth["posture"]["R"], float)
            yield body, name, read_torso(torso_dir / "torso.ply"), yaw_deg(R @ np.array([0.0, 1.0, 0.0]))


def summarise(rows: list) -> dict:
    out = {}
    for name in BANDS:
        e = np.array([r[name]["error_deg"] for r in rows])
        vp = np.array([r[name]["vp_moved_deg"] for r in rows])
        sp = np.array([r[name]["sp_moved_deg"] for r in rows])
        by = {}
        for r in rows:
            by.setdefault(r["body"], {})[r["scan"]] = r[name]["error_deg"]
        resc = np.array([abs(v["baseline"] - v["rescan"]) for v in by.values() if len(v) == 2])
        f = lambda a, fn: float(fn(a)) if np.isfinite(a).any() else None  # noqa: E731
        out[name] = {"scans": len(rows), "failed": int(np.sum(~np.isfinite(e))),
                     "error_mean_deg": f(e, np.nanmean), "error_mean_abs_deg": f(np.abs(e), np.nanmean),
                     "error_max_abs_deg": f(np.abs(e), np.nanmax),
                     "vp_moved_median_deg": f(vp, np.nanmedian), "vp_moved_max_deg": f(vp, np.nanmax),
                     "sp_moved_median_deg": f(sp, np.nanmedian), "sp_moved_max_deg": f(sp, np.nanmax),
                     "rescan_pairs": int(np.isfinite(resc).sum()), "rescan_change_median_deg": f(resc, np.nanmedian),
                     "rescan_change_max_deg": f(resc, np.nanmax)}
    return out


def run(scans, ic, log) -> list:
    rows = []
    for body, name, torso, true_yaw in scans:
        try:
            r = measure_scan(torso, true_yaw, ic)
        except ValueError as exc:
            log(f"  body {body} {name}: failed ({exc})")
            continue
        rows.append({"body": body, "scan": name, **r})
        log(f"  body {body} {name}: " + ", ".join(f"{n} {r[n]['error_deg']:+.2f}" for n in BANDS))
    return rows


def print_table(title: str, s: dict):
    print(f"\n{title}\n| band | yaw error, mean / mean abs / max abs | VP ±6 mm moves it, median / max | "
          "SP ±12 mm moves it, median / max | re-scan change, median / max |\n|---|---|---|---|---|")
    fmt = lambda v: "–" if v is None else f"{v:.2f}"  # noqa: E731
    for name, v in s.items():
        print(f"| {name} | {v['error_mean_deg']:+.2f} / {fmt(v['error_mean_abs_deg'])} / {fmt(v['error_max_abs_deg'])}° "
              f"| {fmt(v['vp_moved_median_deg'])} / {fmt(v['vp_moved_max_deg'])}° "
              f"| {fmt(v['sp_moved_median_deg'])} / {fmt(v['sp_moved_max_deg'])}° "
              f"| {fmt(v['rescan_change_median_deg'])} / {fmt(v['rescan_change_max_deg'])}° ({v['rescan_pairs']} pairs) |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, help="true surfaces: bench_bodies.py's bodies of this seed")
    ap.add_argument("--bodies", type=int, default=10)
    ap.add_argument("--points", type=int, default=80_000)
    ap.add_argument("--rendered", type=Path, help="bench_rescans.py's kept scenarios (e.g. bench-out/rescans-demo/demo)")
    ap.add_argument("--set", default="tune", choices=("tune", "report"), help="which of its sets")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.seed is None and args.rendered is None:
        ap.error("give --seed, --rendered, or both")
    run = provenance(__file__, argv)
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    ic, t0, result = IndicesConfig(), time.perf_counter(), {}
    if args.seed is not None:
        log(f"true surfaces, seed {args.seed}, {args.bodies} bodies:")
        rows = run(true_surface_scans(args.seed, args.bodies, args.points), ic, log)
        result["true_surfaces"] = {"seed": args.seed, "scans": rows, "summary": summarise(rows)}
    if args.rendered is not None:
        if not args.rendered.is_dir():
            ap.error(f"--rendered {args.rendered}: no such directory (run bench_rescans.py with --out first)")
        log(f"rendered re-scans, {args.rendered} ({args.set}):")
        rows = run(rendered_scans(args.rendered, args.set), ic, log)
        if not rows:
            ap.error(f"--rendered {args.rendered}: no reconstructed {args.set}-* torsos there")
        result["rendered"] = {"root": str(args.rendered), "set": args.set, "scans": rows, "summary": summarise(rows)}
    for k, v in result.items():
        print_table(f"{k} ({v.get('seed', v.get('set'))})", v["summary"])
    result.update({**run, "seconds": round(time.perf_counter() - t0, 1)})
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
