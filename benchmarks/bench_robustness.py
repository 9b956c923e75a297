"""Benchmark: one arm's reconstruction under what real patients and rigs bring, against the clean capture and the peers.

    .venv/bin/python benchmarks/bench_robustness.py --preset paper --seed 34 --out bench-out/robustness

Each condition is the same installation, patient and posture as the clean
capture (same seed and session: same rig, lenses, body, noise streams) with
one thing changed (``CONDITIONS``). Only the arm's cameras are rendered (every
projector is on), and no test field: every method reconstructs with the
**true capture-time calibration**, so that the table shows what the condition
does and nothing else. For each condition: ours (``reconstruct_arm``),
StereoSGBM with our surface filters and pycolmap with dense SIFT and the
known poses (tracks of three or more images), as in
``bench_reconstruct_arm.py``: RMS, 95th percentile and worst distance to the
true body, coverage of the torso that two of the arm's cameras see, density,
wall time. Ratios against the clean capture and against each peer are in
the JSON (``--json``). The seed is a reporting seed: nothing was tuned on it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from recon_engine.formats import read_calibration, read_capture, read_rig  # noqa: E402
from recon_engine.parallel import reuse_freed_images  # noqa: E402
from recon_engine.reconstruction import arm_cameras  # noqa: E402
from recon_engine.simulator.config import preset  # noqa: E402
from recon_engine.simulator.rig import make_rig  # noqa: E402
from recon_engine.simulator.scenario import simulate  # noqa: E402

from bench_reconstruct_arm import Truth, measure_arm  # noqa: E402
from provenance import commit as provenance_commit, provenance  # noqa: E402


def _conditions(cfg, **kw):
    return replace(cfg, conditions=replace(cfg.conditions, **kw))


def _subject(cfg, **kw):
    return replace(cfg, subject=replace(cfg.subject, **kw))


def _camera(cfg, **kw):
    return replace(cfg, camera=replace(cfg.camera, **kw))


def _scene(cfg, **kw):
    return replace(cfg, scene=replace(cfg.scene, **kw))


# name -> (what it is, how it changes the clean scenario config); `cam` is the arm's middle camera
CONDITIONS = {
    "clean": ("the clean capture", lambda c, cam: c),
    "dark_skin": ("Fitzpatrick V-VI: albedo 0.12 (clean 0.5); the rig's exposure stays set for albedo 0.5",
                  lambda c, cam: _conditions(_subject(c, albedo=0.12), exposure_albedo=0.5)),
    "dark_skin_exposed": ("the same dark skin, the exposure set for it (the technician's or an auto-exposure's)",
                          lambda c, cam: _subject(c, albedo=0.12)),
    "oily_skin": ("specular highlights: 8 % of the projectors' light reflected in a Blinn-Phong lobe (exponent 30)",
                  lambda c, cam: _conditions(c, specular=0.08, shininess=30.0)),
    "freckles_moles": ("30 freckles per dm2 (1-3 mm, 15-40 % darker) and 15 moles (3-6 mm, 65 % darker)",
                       lambda c, cam: _conditions(c, freckles_per_dm2=30.0, moles=15)),
    "body_hair": ("dark body hair, 3 strands per cm2, 0.06 mm thick, 5-15 mm long",
                  lambda c, cam: _conditions(c, body_hair_per_cm2=3.0)),
    "tattoo": ("a dark 120 x 90 mm tattoo on the back", lambda c, cam: _conditions(c, tattoo=True)),
    "underwear": ("white underwear up to 20 mm above the sacral point, a dark printed waistband, 1 mm fabric step",
                  lambda c, cam: _conditions(c, underwear_top_mm=20.0)),
    "room_light": ("room light on: ambient 0.3 of a lit projector pixel (clean 0.04); exposure follows",
                   lambda c, cam: _scene(c, torso_ambient=0.3)),
    "exposure_over": ("the arm's middle camera +1 EV (highlights saturate)",
                      lambda c, cam: _conditions(c, exposure_ev=((cam, 1.0),))),
    "exposure_under": ("the arm's middle camera -1 EV", lambda c, cam: _conditions(c, exposure_ev=((cam, -1.0),))),
    "defocus": ("cameras focused at 2000 mm instead of 2350, at f/4 instead of f/5.6",
                lambda c, cam: _camera(c, focus_mm=2000.0, f_number=4.0)),
    "jpeg": ("images stored as JPEG at quality 90", lambda c, cam: _conditions(c, jpeg_quality=90)),
    "trigger_jitter": ("cameras triggered 5 ms apart (1-sigma) while the patient sways at 5 mm/s and breathes",
                       lambda c, cam: _conditions(c, trigger_jitter_ms=5.0)),
}


def scenario_for(name: str, preset_name: str, seed: int, arm_ids: list) -> object:
    base = preset(preset_name, seed=seed, captures=(("visit0-a", 0),), torso_cameras=tuple(arm_ids))
    base = replace(base, testfield=replace(base.testfield, poses=0))  # the true calibration: no test field
    return CONDITIONS[name][1](base, arm_ids[len(arm_ids) // 2])


def arm_ids_of(preset_name: str, seed: int, arm: str) -> list:
    """The arm's camera ids, from the rig the preset builds (the rig does not depend on the conditions)."""
    cfg = preset(preset_name, seed=seed)
    rig = make_rig(cfg, np.random.default_rng(seed), 0.0).rig  # only the rig's names are read
    return arm_cameras(rig, arm)


def run_condition(folder: Path, arm: str, peers: set, ours: bool = True) -> dict:
    """One condition's scenario, arm ``arm``: ours and the ``peers``, every method with the true calibration."""
    rig = read_rig(folder / "rig.json")
    cal = read_calibration(folder / "truth" / "visit0-a" / "calibration.json")
    cap = read_capture(folder / "captures" / "visit0-a", rig)
    seen_by = [cal.cameras[c] for c in arm_cameras(rig, arm)]
    return measure_arm(cap, rig, cal, arm, Truth(folder, "visit0-a"), seen_by, peers=peers, ours=ours,
                       pycolmap_work=folder.parent / f"pycolmap-{folder.name}")


def stamped(figures: dict) -> dict:
    """Each method's figures with the commit that measured them (rows can mix runs: ``--keep-peers``)."""
    commit = provenance_commit()
    return {k: ({**v, "commit": commit} if isinstance(v, dict) else v) for k, v in figures.items()}


def ratios(rows: dict) -> dict:
    """Per condition: ours against the clean capture, and each peer's RMS and p95 over ours."""
    clean = rows.get("clean", {}).get("ours")
    out = {}
    for name, row in rows.items():
        ours = row["ours"]
        r = {}
        if clean and ours.get("points"):
            r["rms_vs_clean"] = ours["rms_mm"] / clean["rms_mm"]
            r["coverage_minus_clean"] = ours["coverage"] - clean["coverage"]
        for peer in ("sgbm", "pycolmap"):
            p = row.get(peer)
            if p and p.get("points") and ours.get("points"):
                r[f"{peer}_rms_over_ours"] = p["rms_mm"] / ours["rms_mm"]
                r[f"{peer}_p95_over_ours"] = p["p95_mm"] / ours["p95_mm"]
        out[name] = r
    return out


def markdown(result: dict) -> str:
    """The JSON's conditions as the table of ``docs/benchmarks.md``."""
    def cell(x):
        if not x or not x.get("points"):
            return "not run" if not x else "no points"
        return (f"{x['rms_mm']:.4f} / {x['p95_mm']:.3f} / {x['max_mm']:.2f}, {100 * x['coverage']:.1f} %"
                f" ({x['beyond_2mm']} > 2 mm), {x['seconds']:.0f} s")

    rows = ["| condition | ours: RMS / p95 / max (mm), coverage, time | RMS ÷ clean | SGBM (our filters) | "
            "pycolmap (tracks ≥ 3) | SGBM p95 ÷ ours | pycolmap RMS ÷ ours |", "|---|---|---|---|---|---|---|"]
    ratio = result.get("ratios", {})
    for name, row in result["conditions"].items():
        r = ratio.get(name, {})
        fmt = (lambda k: f"{r[k]:.2f}" if k in r else "")
        rows.append(f"| {name}: {row['what']} | {cell(row['ours'])} | {fmt('rms_vs_clean')} | {cell(row.get('sgbm'))} | "
                    f"{cell(row.get('pycolmap'))} | {fmt('sgbm_p95_over_ours')} | {fmt('pycolmap_rms_over_ours')} |")
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--seed", type=int, default=34, help="a reporting seed (nothing was tuned on it)")
    ap.add_argument("--arm", default="A")
    ap.add_argument("--conditions", nargs="*", default=list(CONDITIONS), choices=list(CONDITIONS))
    ap.add_argument("--peers", default="sgbm,pycolmap", help="comma-separated: sgbm, pycolmap (empty: ours only)")
    ap.add_argument("--out", default="bench-out/robustness", help="scenarios are kept here and reused")
    ap.add_argument("--json", default="bench-out/bench_robustness.json")
    ap.add_argument("--table", action="store_true", help="print the JSON's table in markdown and stop")
    ap.add_argument("--keep-peers", action="store_true",
                    help="run ours (and --peers) again, keeping the other peers' figures already in the JSON: the "
                         "scenarios are rendered the same from the same seed, so the peers' inputs are unchanged")
    ap.add_argument("--add-peers", action="store_true",
                    help="run only --peers on conditions already in the JSON, keeping their other figures")
    args = ap.parse_args()
    run = provenance(__file__)
    if args.table:
        print(markdown(json.loads(Path(args.json).read_text())))
        return 0
    reuse_freed_images()  # as the command line does: the figures are the CLI's
    out = Path(args.out) / f"{args.preset}-s{args.seed}"
    out.mkdir(parents=True, exist_ok=True)
    peers = {p for p in args.peers.split(",") if p}
    ids = arm_ids_of(args.preset, args.seed, args.arm)
    dest = Path(args.json)
    result = json.loads(dest.read_text()) if dest.exists() else {}
    if result.get("preset") != args.preset or result.get("seed") != args.seed:
        result = {}
    result.update({**run,
                   "preset": args.preset, "seed": args.seed, "arm": args.arm,
                   "calibration": "true, capture time (every method)"})
    rows = result.setdefault("conditions", {})
    for name in args.conditions:
        folder = out / name
        t0 = time.perf_counter()
        if not folder.exists():
            simulate(folder, scenario_for(name, args.preset, args.seed, ids), progress=lambda m: None)
        t_sim = time.perf_counter() - t0
        if args.add_peers and name in rows:
            fresh = run_condition(folder, args.arm, peers, ours=False)
            row = {**rows[name], **stamped(fresh)}
        else:
            fresh = stamped(run_condition(folder, args.arm, peers))
            row = {**rows.get(name, {}), **fresh} if args.keep_peers else fresh
            row["what"] = CONDITIONS[name][0]
            row["simulated_s"] = t_sim
        rows[name] = row
        print(name, json.dumps({k: {kk: (round(vv, 4) if isinstance(vv, float) else vv) for kk, vv in v.items()}
                                for k, v in row.items() if isinstance(v, dict)}), flush=True)
        result["ratios"] = ratios(rows)
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_text(json.dumps(result, indent=2))  # after every condition: a long run keeps what it measured
    print(f"raw figures: {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
