"""Clinical indices across bodies the analysis was not tuned on: landmarks, indices, noise verdicts.

Every body is drawn from the simulator's family (``SubjectConfig``: stature 1300-1800 mm, slim to heavy
builds, girls' breasts and hips, arms hanging closer or raised, hair over the neck for some, the scan's
top anywhere from C7 to above the chin) with a C or S curve of 4-12 deg at its apex (1.6 mm of lateral
deviation per degree). Per body: a baseline, a same-day re-scan (sway up to 1.5 deg and 5 mm, other
breathing, a new sampling) and progressions of +5 deg / +8 mm and +10 deg / +16 mm at the apex.

Scans are the true posed surfaces sampled as the rig sees them (``analysis.synthetic.scan_surface``:
two cameras of an arm, 0.07 mm noise along the normal, 80 000 points), not rendered reconstructions: the
figures are the analysis's own, on top of which the reconstruction's error (0.03 mm RMS at paper scale)
adds little.

Two sets of bodies, never mixed: ``tune`` (seeds ``--tune-seed``, default 100) gives the scanner's
repeatability (the MDC of every index from its same-day re-scans: ``--write-mdc`` writes it to
``analysis/scanner_mdc.json``, the clinic's fall-back until it has repeat pairs of its own) and is where
the analysis's defaults may be chosen; ``report`` (held out, ``--report-seed``, default 200) is measured
against that MDC.

``--arms-crossed`` draws the held-out bodies (and their scans and clicks) exactly as without it, each with its
forearms crossed in front of the chest instead of its drawn arm abduction: a paired comparison. ``--mdc-file``
judges against a stored MDC (``analysis/scanner_mdc.json``) instead of running the tuning bodies
(``--tune-bodies 0``).

A scan on which the analysis asks for a trunk landmark (VP or SP: "not measurable on this scan: mark the
landmark") is analysed again with that landmark marked as a clinician would, the simulator's point plus a
click's error (``CLICK_SIGMA_MM`` per axis, its own random stream), as ``bench_rescans.py`` does; it counts
under ``declined`` (why) and ``marked``.

Prints and writes (``--json``): each landmark's error against the truth and its re-scan spread; each
index's error against its true value and its re-scan change; the share of re-scans and progressions
flagged beyond the MDC; the scans declined (not measurable) and why.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from analysis.indices import CORE_LANDMARKS, analyse_torso  # noqa: E402
from analysis.profiles import cobb_estimate, sagittal_angles  # noqa: E402
from analysis.repeatability import flatten, index_changes, mdc_from_index_pairs  # noqa: E402
from analysis.synthetic import scan_surface  # noqa: E402
from provenance import provenance  # noqa: E402
from recon_engine.simulator.config import preset  # noqa: E402
from recon_engine.simulator.bodies import curve_profiles  # noqa: E402
from recon_engine.simulator.posed import posed_subject, posture_like  # noqa: E402
from recon_engine.simulator.rig import rotation_about  # noqa: E402

LANDMARK_KEYS = ("vertebra_prominens", "sacral_point", "dimple_left", "dimple_right")
FIGURES = ("surface_rotation_deg.max", "surface_rotation_deg.rms", "lateral_deviation_mm.max",
           "lateral_deviation_mm.rms", "spine_lateral_deviation_mm.max", "midline_rotation_deg.max", "hump_mm",
           "trunk_imbalance_mm", "trunk_length_mm", "asymmetry_mm", "kyphotic_angle_deg", "lordotic_angle_deg",
           "cobb_estimate_deg.max", "pelvic_obliquity_mm", "pelvic_torsion_deg")
MDC_MIN_BODIES = 10
CLICK_SIGMA_MM = 2.0  # a clinician's mark on the torso picture, 1-sigma per axis
# the true Cobb angles: the simulated spine's frontal line smoothed over about a vertebra's height (the end
# vertebrae's endplates average the line over one; unsmoothed, the simulator's line has 1-2 deg wiggles where
# its two curves' shapes join, which no radiograph would call curves), read as the estimate reads its own line
TRUE_COBB_SMOOTH_MM = 20.0
CURVE_MATCH_LEVELS = 0.2  # an estimated curve stands for a true one of its side with its apex this close


def true_symmetry_deviation(subject, rep):
    """The simulated skin's own symmetry line against the true SP-VP line (mm, + right).

    Returns (signed max over the levels 0.05-0.95, value at the level where the measured maximum lies).
    """
    P = np.asarray(subject["symmetry_line"])
    lm = subject["landmarks"]
    sp, vp = np.asarray(lm["sacral_point"]), np.asarray(lm["vertebra_prominens"])
    f = (P[:, 2] - sp[2]) / (vp[2] - sp[2])
    left = subject["posture"].R @ np.array([1.0, 0.0, 0.0])  # the body's +X is the patient's left
    dev = -((P - (sp + f[:, None] * (vp - sp))) @ left)
    inside = (f > 0.05) & (f < 0.95)
    k = int(np.argmax(np.abs(dev[inside])))
    order = np.argsort(f)
    return float(dev[inside][k]), float(np.interp(rep["apex"]["lateral_deviation"]["level"], f[order], dev[order]))


def draw_body(rng: np.random.Generator) -> dict:
    """One subject of the family: its SubjectConfig overrides, curve, and the scan's top above C7 (mm)."""
    girl = rng.random() < 0.5
    heavy = rng.random()
    body = {
        "stature_mm": float(rng.uniform(1300, 1800)),
        "build_width": float(0.88 + 0.32 * heavy + rng.normal(0, 0.03)),
        "build_depth": float(0.85 + 0.5 * heavy + rng.normal(0, 0.04)),
        "belly_mm": float(max(0.0, 45 * (heavy - 0.5) + rng.normal(0, 5))),
        "breasts_mm": float(rng.uniform(12, 32)) if girl else 0.0,
        "hips": float(rng.uniform(1.03, 1.12)) if girl else 1.0,
        "arm_abduction_deg": float(rng.uniform(-25, 30)),
        "neck_hair_mm": float(rng.uniform(12, 25)) if girl and rng.random() < 0.5 else 0.0,
        "curve": "C" if rng.random() < 0.4 else "S",
        "thoracic_apex": float(rng.uniform(0.55, 0.7)),
        # fat fills the dimples of a heavy body
        "dimples_mm": float(max(0.0, rng.uniform(2.0, 6.0) * (1.2 - heavy))),
        "pelvic_obliquity_mm": float(rng.uniform(-10, 10)),
    }
    rot = float(rng.uniform(4, 12))
    return {"subject": body, "rotation_deg": rot, "lateral_mm": 1.6 * rot, "top_mm": float(rng.uniform(-10, 200)),
            "girl": girl}


def scan(cfg, rotation_deg, lateral_mm, top_mm, rng, n_points):
    yaw, shift = rng.uniform(-1.5, 1.5), np.r_[rng.uniform(-5, 5, 2), 0.0]
    posture = posture_like(cfg, rotation_deg, lateral_mm, breathing=rng.uniform(-0.5, 0.5),
                           R=rotation_about([0, 0, 1], yaw), t=shift)
    s = posed_subject(cfg, posture=posture)
    z = s["vertices"][s["triangles"]].mean(axis=1)[:, 2]
    lm = s["landmarks"]
    region = (z > lm["sacral_point"][2] - 150.0) & (z < lm["vertebra_prominens"][2] + top_mm)
    t = scan_surface(s["vertices"], s["triangles"], region, n_points=n_points, seed=int(rng.integers(1 << 30)))
    s["true_profiles"] = true_profiles(cfg, s)
    s["dimples_mm"] = cfg.subject.dimples_mm
    return s, t


def true_profiles(cfg, s) -> dict:
    """The true kyphotic/lordotic angles (the same definition on the true skin line over the spinous
    processes, between the true landmarks), the true Cobb angle of the simulated spine's frontal curve, and
    the true pelvic obliquity (between the true dimples)."""
    p = s["posture"]
    lm = {k: p.R.T @ (np.asarray(v) - p.t) for k, v in s["landmarks"].items() if v is not None}
    line = (s["symmetry_line"] - p.t) @ p.R  # the patient frame: x left, y posterior, z up
    z_sp, z_vp = lm["sacral_point"][2], lm["vertebra_prominens"][2]
    out = {}
    sag = sagittal_angles(line[:, 2], line[:, 1], z_sp, z_vp)
    if sag:
        out["kyphotic_angle_deg"], out["lordotic_angle_deg"] = sag["kyphotic_angle_deg"], sag["lordotic_angle_deg"]
    levels = np.linspace(0, 1, 401)
    lateral, _ = curve_profiles(levels, cfg.subject, p.rotation_deg, p.lateral_mm)
    cobb = cobb_estimate(z_sp + levels * (z_vp - z_sp), lateral, z_sp, z_vp, step_mm=1.0,
                         smooth_mm=TRUE_COBB_SMOOTH_MM)
    if cobb and cobb["major"]:
        out["cobb_estimate_deg.max"] = cobb["major"]["value_deg"] * (1 if cobb["major"]["side"] == "right" else -1)
        out["cobb_curves"] = cobb["curves"]
    if "dimple_left" in lm:
        out["pelvic_obliquity_mm"] = float(lm["dimple_right"][2] - lm["dimple_left"][2])
    return out


def analyse_as_clinic(torso, true_landmarks: dict, clicks: np.random.Generator):
    """The analysis as the clinic runs it: automatically, then, where it asks for a trunk landmark (VP, SP),
    again with that landmark marked as a clinician would: the simulator's point (``true_landmarks``, the
    torso's frame, mm) plus a click's error (``CLICK_SIGMA_MM`` per axis, drawn from ``clicks``).

    Returns ``(TorsoAnalysis, names marked, the automatic analysis's report)``; raises ``ValueError`` as
    ``analyse_torso`` does."""
    a = analyse_torso(torso)
    mark = [n for n in (a.report.get("not_measurable") or {}).get("mark", []) if n in CORE_LANDMARKS
            and true_landmarks.get(n) is not None]
    if not mark:
        return a, [], a.report
    marks = {n: (np.asarray(true_landmarks[n]) + clicks.normal(0, CLICK_SIGMA_MM, 3)).tolist() for n in mark}
    return analyse_torso(torso, landmarks=marks), sorted(mark), a.report


def measure(subject, torso, clicks: np.random.Generator) -> dict:
    """One scan analysed as the clinic does (:func:`analyse_as_clinic`), against the simulator's truth."""
    t0 = time.perf_counter()
    try:
        a, mark, first = analyse_as_clinic(torso, subject["landmarks"], clicks)
    except ValueError as exc:
        return {"declined": f"failed: {exc}", "seconds": time.perf_counter() - t0}
    rep = a.report
    declined = (first.get("not_measurable") or {}).get("reason")
    out = {"seconds": time.perf_counter() - t0, "report": rep, "flat": flatten(rep), "marked": mark}
    post = subject["posture"].R @ np.array([0.0, 1.0, 0.0])
    out["facing_ok"] = bool(np.asarray(rep["frame"]["posterior"]) @ post > 0.7)
    out["facing_status"] = rep["frame"]["facing"]["status"]
    out["landmark_error"] = {k: (np.asarray(rep["landmarks"][k]["position_mm"]) - subject["landmarks"][k]).tolist()
                             for k in LANDMARK_KEYS if rep["landmarks"].get(k, {}).get("position_mm") is not None
                             and subject["landmarks"].get(k) is not None}
    out["landmark_confidence"] = {k: rep["landmarks"][k].get("confidence") for k in LANDMARK_KEYS}
    out["dimples_mm"] = subject["dimples_mm"]
    if declined:  # what the analysis declined on its own, before any mark
        out["declined"] = declined
    i = int(np.argmax(np.abs(subject["curve"]["rotation_deg"])))
    out["truth"] = {"surface_rotation_deg.max": float(subject["curve"]["rotation_deg"][i]),
                    **subject["true_profiles"]}
    if rep.get("apex"):
        out["truth"]["lateral_deviation_mm.max"] = true_symmetry_deviation(subject, rep)[0]
    return out


VISITS = (("baseline", (0, 0)), ("rescan", (0, 0)), ("plus5", (5, 8)), ("plus10", (10, 16)))  # +deg, +mm at the apex


def draw_scans(seed: int, n_bodies: int, n_points: int, arms_crossed: bool = False):
    """Each body of the family and its four scans (``VISITS``), in the order the seed's random stream draws
    them: yields ``(body, draw, visit, posed subject, torso)``. With ``arms_crossed`` every body is the one the
    seed draws, its forearms crossed in front of the chest instead of its arms' drawn abduction (the same
    bodies, scans and clicks otherwise: a paired comparison)."""
    rng = np.random.default_rng(seed)
    base = preset("paper")
    for b in range(n_bodies):
        draw = draw_body(rng)
        if arms_crossed:
            draw["subject"] = {**draw["subject"], "arm_abduction_deg": 0.0, "arms_crossed": True}
        cfg = replace(base, subject=replace(base.subject, **draw["subject"]))
        for name, (drot, dlat) in VISITS:
            s, t = scan(cfg, draw["rotation_deg"] + drot, draw["lateral_mm"] + dlat, draw["top_mm"], rng, n_points)
            yield b, draw, name, s, t


def run_set(seed: int, n_bodies: int, n_points: int, log, arms_crossed: bool = False) -> list[dict]:
    # the clinician's clicks have their own stream, as in bench_rescans: the bodies drawn do not depend on
    # which scans the analysis asked to be marked
    clicks = np.random.default_rng([seed, 1])
    bodies = []
    for b, draw, name, s, t in draw_scans(seed, n_bodies, n_points, arms_crossed):
        if name == VISITS[0][0]:
            bodies.append({"body": b, "draw": draw, "scans": {}})
        rec = bodies[-1]
        rec["scans"][name] = measure(s, t, clicks)
        if name != VISITS[-1][0]:
            continue
        sc = rec["scans"]
        log(f"  body {b:2d} ({'girl' if draw['girl'] else 'boy '}, {draw['subject']['stature_mm']:.0f} mm, "
            f"w {draw['subject']['build_width']:.2f} d {draw['subject']['build_depth']:.2f}, "
            f"top C7+{draw['top_mm']:.0f}): rotation "
            + ", ".join(f"{k} {v['flat'].get('surface_rotation_deg.max', float('nan')):+.1f}" if "flat" in v
                        else f"{k} -" for k, v in sc.items())
            + ("; declined: " + "; ".join(sorted({v['declined'][:60] for v in sc.values() if 'declined' in v}))
               if any('declined' in v for v in sc.values()) else "")
            + ("; marked: " + ", ".join(f"{k} {'+'.join(v['marked'])}" for k, v in sc.items() if v.get("marked"))
               if any(v.get("marked") for v in sc.values()) else ""))
    return bodies


def repeat_pairs(bodies):
    return [(b["scans"]["baseline"]["report"], b["scans"]["rescan"]["report"]) for b in bodies
            if "report" in b["scans"]["baseline"] and "report" in b["scans"]["rescan"]]


def same_side_error(report: dict, key: str, truth: float):
    """The measured size on the truth's side (+ right, - left) minus the truth, for a sided ``X.max``; else None."""
    base, _, leaf = key.partition(".")
    entry = report.get(base)
    if leaf != "max" or not isinstance(entry, dict) or not ("right" in entry or "left" in entry):
        return None
    if entry.get("max") is None:  # withheld on this scan (not measurable): no size to compare
        return None
    side = "right" if truth >= 0 else "left"
    size = (entry.get(side) or {}).get("size")
    size = float(size) if isinstance(size, (int, float)) else 0.0  # no extreme on that side: it read nothing there
    return (size if side == "right" else -size) - truth


def summarise(bodies, mdc) -> dict:
    out = {"bodies": len(bodies), "scans": 4 * len(bodies)}
    scans = [s for b in bodies for s in b["scans"].values()]
    measured = [s for s in scans if "report" in s]
    out["facing_wrong"] = sum(not s["facing_ok"] for s in measured)
    out["facing_uncertain"] = sum(s["facing_status"] != "certain" for s in measured)
    declined = [s["declined"] for s in scans if "declined" in s]
    out["declined"] = len(declined)
    out["declined_reasons"] = sorted({d.split(":")[1].split("(")[0].strip() if ":" in d else d for d in declined})
    out["marked"] = {k: sum(k in s.get("marked", ()) for s in scans) for k in CORE_LANDMARKS}
    lm = {}
    for k in LANDMARK_KEYS:
        err = [np.linalg.norm(s["landmark_error"][k]) for s in measured
               if s["landmark_confidence"][k] == "high" and k in s["landmark_error"]]
        spread = [np.linalg.norm(np.subtract(b["scans"]["baseline"]["landmark_error"][k],
                                             b["scans"]["rescan"]["landmark_error"][k]))
                  for b in bodies if all("report" in b["scans"][n] and b["scans"][n]["landmark_confidence"][k] == "high"
                                         and k in b["scans"][n]["landmark_error"] for n in ("baseline", "rescan"))]
        lm[k] = {"error_mm": {"median": float(np.median(err)), "p95": float(np.percentile(err, 95)),
                              "max": float(np.max(err))} if err else None,
                 "rescan_spread_mm": {"median": float(np.median(spread)), "max": float(np.max(spread)),
                                      "within_5mm": f"{sum(x <= 5 for x in spread)}/{len(spread)}"} if spread else None}
    out["landmarks"] = lm
    # the dimples found with confidence, by how deep the body's dimples were
    for lo, hi in ((0.0, 1.5), (1.5, 3.5), (3.5, 10.0)):
        sel = [s for s in measured if lo <= s["dimples_mm"] < hi]
        found = sum(s["landmark_confidence"]["dimple_left"] == "high" for s in sel)
        out.setdefault("dimples_found", {})[f"{lo:g}-{hi:g} mm deep"] = f"{found}/{len(sel)}"
        # the automatic (suggested) dimples against the simulator's, each side of each scan
        err = [np.linalg.norm(s["landmark_error"][k]) for s in sel for k in ("dimple_left", "dimple_right")
               if k in s["landmark_error"]]
        suggested = [s for s in sel if s["report"]["landmarks"]["dimple_left"]["method"].startswith("suggested")]
        out.setdefault("dimples_automatic", {})[f"{lo:g}-{hi:g} mm deep"] = {
            "error_mm_median": float(np.median(err)) if err else None,
            "within_6mm": f"{sum(e <= 6 for e in err)}/{len(err)}", "scans_suggested": f"{len(suggested)}/{len(sel)}"}
    idx = {}
    for k in FIGURES:
        rows = {}
        err = [s["flat"][k] - s["truth"][k] for s in measured if k in s["flat"] and k in s.get("truth", {})]
        if err:
            rows["error"] = {"mean": float(np.mean(err)), "mean_abs": float(np.mean(np.abs(err))),
                             "max_abs": float(np.max(np.abs(err)))}
        # a signed maximum whose two sides are nearly equal (an S curve) may be the other side's than the truth's:
        # its size error is then taken on the truth's side (what the clinic reads there), its side choice apart
        same = [e for e in (same_side_error(s["report"], k, s["truth"][k]) for s in measured
                            if k in s.get("truth", {})) if e is not None]
        if same:
            rows["error_on_the_truths_side"] = {
                "mean": float(np.mean(same)), "mean_abs": float(np.mean(np.abs(same))),
                "max_abs": float(np.max(np.abs(same))),
                "other_side_largest": f"{sum(np.sign(s['flat'].get(k, 0)) != np.sign(s['truth'][k]) for s in measured if k in s.get('truth', {}) and k in s['flat'])}/{len(same)}"}
        # the change as the clinic computes it (a signed maximum side by side: analysis.repeatability)
        ch = [c[k]["change"] for c in (index_changes(b["scans"]["baseline"]["report"], b["scans"]["rescan"]["report"],
                                                     figures=(k,))
                                       for b in bodies if all("report" in b["scans"][n] for n in ("baseline", "rescan")))
              if k in c]
        if ch:
            rows["rescan_change"] = {"mean_abs": float(np.mean(np.abs(ch))), "max_abs": float(np.max(np.abs(ch)))}
        # scans whose final analysis (after any VP / SP mark) still withholds it: the pelvic figures without marked
        # dimples, the surface rotation where the sections at an apex cannot be read
        rows["withheld"] = f"{sum(k.split('.')[0] in ((s['report'].get('not_measurable') or {}).get('indices') or []) for s in measured)}/{len(measured)}"
        m = (mdc.get(k) or {}).get("mdc")
        rows["mdc"] = m
        for name in ("rescan", "plus5", "plus10"):
            flags = [index_changes(b["scans"]["baseline"]["report"], b["scans"][name]["report"], {k: m})
                     .get(k, {}).get("exceeds_mdc") for b in bodies
                     if "report" in b["scans"]["baseline"] and "report" in b["scans"][name]]
            flags = [f for f in flags if f is not None]
            rows[f"flagged_{name}"] = f"{sum(flags)}/{len(flags)}" if flags else None
        idx[k] = rows
    out["indices"] = idx
    out["cobb_curves"] = cobb_curve_errors(bodies)
    out["seconds_per_scan"] = float(np.median([s["seconds"] for s in scans]))
    return out


def match_curves(estimated: list, true: list) -> list:
    """``(true curve, estimated curve or None)`` for every true curve: one to one, the closest apexes of the same
    side first, within :data:`CURVE_MATCH_LEVELS` (a true curve left without one was missed)."""
    near = sorted((abs(c["apex_level"] - t["apex_level"]), i, j) for i, t in enumerate(true)
                  for j, c in enumerate(estimated)
                  if c["side"] == t["side"] and abs(c["apex_level"] - t["apex_level"]) <= CURVE_MATCH_LEVELS)
    pair, used = {}, set()
    for _, i, j in near:
        if i not in pair and j not in used:
            pair[i] = j
            used.add(j)
    return [(t, estimated[pair[i]] if i in pair else None) for i, t in enumerate(true)]


def cobb_curve_errors(bodies) -> dict:
    """Every true curve's Cobb estimate against the truth, the curves missed and the extra ones, the major
    curve's side, and each curve's same-day re-scan change."""
    err, missed, extra, major, majors, double, change = [], 0, 0, 0, 0, 0, []
    for b in bodies:
        got = {}
        for name, s in b["scans"].items():
            est = ((s.get("report") or {}).get("cobb_estimate") or {})
            true = s.get("truth", {}).get("cobb_curves")
            if "curves" not in est or true is None:
                continue
            pairs = match_curves(est["curves"], true)
            got[name] = pairs
            err += [c["value_deg"] - t["value_deg"] for t, c in pairs if c is not None]
            missed += sum(c is None for _, c in pairs)
            extra += len(est["curves"]) - sum(c is not None for _, c in pairs)
            if est["major"] and true:
                majors += 1
                t_major = max(true, key=lambda c: c["value_deg"])
                major += est["major"]["side"] == t_major["side"]
                double += bool(est["double_major"])
        if "baseline" in got and "rescan" in got:
            for (t, a), (_, c) in zip(got["baseline"], got["rescan"]):
                if a is not None and c is not None:
                    change.append(c["value_deg"] - a["value_deg"])
    err, change = np.array(err), np.array(change)
    return {"true_curves": int(len(err) + missed), "matched": int(len(err)), "missed": int(missed),
            "extra": int(extra),
            "error_deg": {"mean": float(err.mean()), "mean_abs": float(np.abs(err).mean()),
                          "max_abs": float(np.abs(err).max())} if len(err) else None,
            "rescan_change_deg": {"mean_abs": float(np.abs(change).mean()), "max_abs": float(np.abs(change).max()),
                                  "pairs": int(len(change))} if len(change) else None,
            "major_on_the_truths_side": f"{major}/{majors}", "double_major": f"{double}/{majors}"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tune-seed", type=int, default=100)
    ap.add_argument("--report-seed", type=int, default=200)
    ap.add_argument("--tune-bodies", type=int, default=12)
    ap.add_argument("--report-bodies", type=int, default=12)
    ap.add_argument("--points", type=int, default=80_000)
    ap.add_argument("--json", help="write the summaries here")
    ap.add_argument("--write-mdc", action="store_true", help="write the tuning set's MDC to analysis/scanner_mdc.json")
    ap.add_argument("--mdc-file", help="judge against the MDC stored here (analysis/scanner_mdc.json's 'mdc') "
                                       "instead of the tuning bodies' (run none with --tune-bodies 0)")
    ap.add_argument("--arms-crossed", action="store_true",
                    help="the held-out bodies' forearms crossed in front of the chest (the same bodies otherwise)")
    args = ap.parse_args(argv)
    if args.write_mdc and (args.mdc_file or args.arms_crossed):
        ap.error("--write-mdc writes the tuning bodies' MDC: not with --mdc-file or --arms-crossed")
    if not args.tune_bodies and not args.mdc_file:
        ap.error("--tune-bodies 0 needs --mdc-file: the held-out bodies are judged against a tuning set's MDC")
    run = provenance(__file__, argv)
    commit = run["commit"]
    t0 = time.perf_counter()
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    log(f"tuning bodies (seed {args.tune_seed}):")
    tune = run_set(args.tune_seed, args.tune_bodies, args.points, log)
    if args.mdc_file:
        stored = json.loads(Path(args.mdc_file).read_text(encoding="utf-8"))
        if "mdc" not in stored:
            raise SystemExit(f"{args.mdc_file}: no 'mdc' (an analysis/scanner_mdc.json is needed)")
        mdc, run["mdc_source"] = stored["mdc"], f"{args.mdc_file}: {stored.get('source', '')}"
    else:
        mdc = mdc_from_index_pairs(repeat_pairs(tune))
    log(f"held-out bodies (seed {args.report_seed}{', arms crossed' if args.arms_crossed else ''}):")
    report = run_set(args.report_seed, args.report_bodies, args.points, log, args.arms_crossed)
    run["arms_crossed"] = args.arms_crossed
    result = {**run, "seconds": time.perf_counter() - t0,
              "tune": summarise(tune, mdc) if tune else None, "report": summarise(report, mdc), "mdc": mdc}
    for name in ("tune", "report"):
        if result[name] is not None:
            log(f"\n{name}: " + json.dumps(result[name], indent=1))
    if args.write_mdc:
        path = ROOT / "analysis" / "scanner_mdc.json"
        # the reconstructed re-scans' sets (bench_rescans.py --write-mdc) stay
        rigs = json.loads(path.read_text(encoding="utf-8")).get("rigs") if path.exists() else None
        out = {"source": "scanner repeatability: same-day re-scans of simulated bodies (benchmarks/bench_bodies.py, "
                         f"seed {args.tune_seed}, {len(repeat_pairs(tune))} pairs, commit {commit})",
               "pairs": len(repeat_pairs(tune)), "mdc": {k: v for k, v in mdc.items()}, **({"rigs": rigs} if rigs else {})}
        path.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
