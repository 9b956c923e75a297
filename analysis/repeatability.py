"""Repeatability of the rig and the minimal detectable change (MDC) of every figure.

From pairs of captures of the same subject close in time (no real change):

- an index measured on both captures (``a_i``, ``b_i``): standard error of
  measurement ``SEM = sqrt(sum (a_i - b_i)^2 / (2 n))``;
- a comparison figure, itself a change between two captures (``D_i``, e.g. a
  region's mean signed distance), has ``SD(D) = sqrt(mean D_i^2)`` around a
  true change of zero, i.e. ``SEM = SD(D) / sqrt(2)``.

In both cases ``MDC95 = 1.96 · sqrt(2) · SEM``: the smallest change between two
captures that exceeds the measurement error with 95 % confidence (Weir 2005;
de Vet et al. 2006). That is a point estimate: from ``n`` pairs the SEM itself
is uncertain (chi-square on ``n`` degrees of freedom), and a threshold at the
estimate flags a re-scan whenever the pairs happened to be quieter than the
scanner (on 10 held-out bodies, 1-3 of 10 same-day re-scans were flagged on
six indices with it). So the ``mdc`` a change is judged against is the upper
bound of the MDC95's own 95 % confidence interval (``mdc_estimate`` keeps the
point estimate): x1.75 from 10 pairs, x1.45 from 20, x1.25 from 50. A change
beyond it exceeds the measurement error even if the scanner were as noisy as
the pairs allow.
"""

from __future__ import annotations

import math

import numpy as np

Z95 = 1.96


def flatten(d: dict, prefix: str = "") -> dict:
    """Numeric leaves of a nested dict as ``{"a.b.c": value}`` (lists and non-numbers left out)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool) and v is not None and math.isfinite(v):
            out[key] = float(v)
    return out


INDEX_FIGURES = ("lateral_deviation_mm.rms", "lateral_deviation_mm.max", "surface_rotation_deg.rms",
                 "surface_rotation_deg.max", "spine_lateral_deviation_mm.rms", "spine_lateral_deviation_mm.max",
                 "midline_rotation_deg.rms", "midline_rotation_deg.max", "hump_mm", "hump_angle_deg",
                 "trunk_imbalance_mm", "trunk_inclination_mm", "trunk_length_mm", "asymmetry_mm",
                 "kyphotic_angle_deg", "lordotic_angle_deg", "pelvic_obliquity_mm", "pelvic_torsion_deg",
                 "cobb_estimate_deg.max")


# figures the spec keeps as one signed number, whose sides the report gives under another key
SIDED_SCALARS = {"hump_mm": "hump", "hump_angle_deg": "hump_angle"}


def _side_sizes(report: dict, key: str):
    """``{"right": size, "left": size}`` of an index that reports each side's largest value (``X.max`` of an index
    with ``right`` / ``left`` entries, or a signed figure of :data:`SIDED_SCALARS`; a side without one is 0), or
    None."""
    base, _, leaf = key.partition(".")
    if key in SIDED_SCALARS:
        base, leaf = SIDED_SCALARS[key], "max"
    entry = report.get(base)
    if leaf != "max" or not isinstance(entry, dict) or not ("right" in entry or "left" in entry):
        return None
    sizes = {}
    for side in ("right", "left"):
        size = (entry.get(side) or {}).get("size")
        sizes[side] = float(size) if isinstance(size, (int, float)) and math.isfinite(size) else 0.0
    return sizes


def _side_changes(earlier: dict, later: dict, key: str) -> list | None:
    """Each side's change of a figure that reports each side's largest value (``X.max``), or None.

    ``[{"side", "earlier", "later", "change"}]`` (values signed by the side: + the patient's right; a side
    without a value reads 0.0), the side larger on the later scan first. An S curve has a curve on each side:
    a page that showed only the side that changed most would show the smaller curve's figures under
    "largest" while the visit page shows the larger one."""
    sa, sb = _side_sizes(earlier, key), _side_sizes(later, key)
    if sa is None or sb is None:
        return None
    out = []
    for side in sorted(("right", "left"), key=lambda s: (-sb[s], s != "right")):
        sign = 1.0 if side == "right" else -1.0
        # (+ 0.0: no -0.0 for a side without a value)
        out.append({"side": side, "earlier": sign * sa[side] + 0.0, "later": sign * sb[side] + 0.0,
                    "change": sign * (sb[side] - sa[side]) + 0.0})
    return out


def _figure_change(earlier: dict, later: dict, fa: dict, fb: dict, key: str):
    """``(earlier, later, sides)`` of one figure for its change, or None when either scan lacks it.

    A signed maximum (``X.max``: + the patient's right) can jump sides between two scans of the same back
    when its two sides are nearly equal (an S curve): +8.0 deg on one scan, -7.9 deg on the re-scan, a
    "change" of 15.9 deg that is no change. Such a figure is compared side by side instead: each side's
    largest value against the same side's, and the side that changed most gives ``earlier`` and ``later``
    (signed by its side); ``sides`` is :func:`_side_changes` (None for a figure without sides).
    """
    if key not in fa or key not in fb:
        return None
    sides = _side_changes(earlier, later, key)
    if sides is None:
        return fa[key], fb[key], None
    most = max(sides, key=lambda s: (abs(s["change"]), s["side"] == "right"))
    return most["earlier"], most["later"], sides


# figures read at their apex, inside the trunk, that do not move with where its ends are put: still judged when a
# trunk landmark was placed two ways. Every other figure rests on the ends (the landmarks' own offsets, the lateral
# deviations on the line joining them, the RMS figures, the sagittal angles, the Cobb estimate and the asymmetry
# on the stretch between them): on the rendered demo re-scans (bench_rescans.py, 2026-12-04) the one held-out
# re-scan flagged (the spine midline's RMS, -2.09 mm; the lateral deviation's RMS -1.79 mm) had its sacral point
# marked on one scan and found on the other, 17-18 mm apart; the largest rotation and the hump of such pairs
# moved within their MDC
APEX_FIGURES = ("surface_rotation_deg.max", "midline_rotation_deg.max", "hump_mm", "hump_angle_deg")
# the pelvic figures rest on the lumbar dimples, which are only ever marked (automatic ones are suggestions)
PELVIC_FIGURES = ("pelvic_obliquity_mm", "pelvic_torsion_deg")


def placed_differently(earlier: dict, later: dict) -> list:
    """The trunk landmarks (VP, SP) a clinician marked on one scan and the analysis found on the other.

    The automatic rules and a clinician's mark do not put a landmark on the same spot (the automatic SP sat
    13-23 mm lower than the marked one on the rendered re-scans): between two such scans the landmarks' own
    offsets change by that much with no change in the patient. On the tuning re-scans (seed 100), the four
    pairs placed differently had the four largest trunk-length changes (13-19 mm; the others 1-13 mm)."""
    out = []
    for k in ("vertebra_prominens", "sacral_point"):
        sa = ((earlier.get("landmarks") or {}).get(k) or {}).get("source")
        sb = ((later.get("landmarks") or {}).get(k) or {}).get("source")
        if sa and sb and (sa == "clinician") != (sb == "clinician"):
            out.append(k)
    return out


def mdc_from_index_pairs(pairs, figures=INDEX_FIGURES) -> dict:
    """MDC of each index from repeat pairs of ``torso-indices/1`` reports: ``{figure: {"sem", "mdc", "n"}}``.

    A signed maximum's change is taken side by side (:func:`_figure_change`), as :func:`index_changes` does.
    Pairs whose VP or SP was placed two ways (:func:`placed_differently`) stay in: such comparisons are judged on
    the apex and pelvic figures only, but without them too few pairs would remain for an MDC (6 of 10 on the
    rendered tuning re-scans), and with them the MDC errs on the side of flagging less."""
    diffs = {}
    for a, b in pairs:
        fa, fb = flatten(a), flatten(b)
        for k in figures:
            pair = _figure_change(a, b, fa, fb, k)
            if pair is not None:
                diffs.setdefault(k, []).append(pair[0] - pair[1])
    out = {}
    for k, d in diffs.items():
        d = np.asarray(d)
        sem = float(np.sqrt(np.sum(d ** 2) / (2 * len(d))))
        out[k] = judged_mdc(Z95 * math.sqrt(2) * sem, sem, len(d))
    return out


def judged_mdc(estimate: float, sem: float, n: int, **extra) -> dict:
    """An MDC entry: the point estimate ``mdc_estimate``, its 95 % interval ``ci95`` from ``n`` pairs, and the
    ``mdc`` changes are judged against (the interval's upper bound: see the module's docstring)."""
    ci = mdc_interval(estimate, n)
    return {"sem": float(sem), "mdc": ci[1], "mdc_estimate": float(estimate), "n": int(n), "ci95": ci, **extra}


COMPARISON_FIGURES = ("average_normal_distance_mm", "signed_distance_mm.mean", "signed_distance_mm.p05",
                      "signed_distance_mm.p95")


def mdc_from_comparisons(reports) -> dict:
    """MDC of each comparison figure from ``torso-comparison/1`` reports of repeat pairs.

    Covers the headline figures and every region's ``mean``, ``p05``, ``p95``
    and ``mean_abs``. Figures that are a spread rather than a signed change
    (average normal distance, mean_abs, p05, p95) are not zero without change:
    their MDC is the repeat value plus 1.96 times its spread over the pairs
    (one pair: the spread is taken as half the repeat value).
    """
    vals = {}
    for r in reports:
        f = flatten(r)
        keys = [k for k in f if k in COMPARISON_FIGURES or (k.startswith("regions.") and
                                                            k.rsplit(".", 1)[-1] in ("mean", "p05", "p95", "mean_abs"))]
        for k in keys:
            vals.setdefault(k, []).append(f[k])
    out = {}
    for k, v in vals.items():
        v = np.asarray(v)
        last = k.rsplit(".", 1)[-1]
        if last == "mean":  # a signed change, zero without change
            sd = float(np.sqrt(np.mean(v ** 2)))
            out[k] = judged_mdc(Z95 * sd, sd / math.sqrt(2), len(v), kind="signed change")
        else:  # a spread: the repeat level plus its own variability
            level = float(np.mean(np.abs(v)))
            spread = float(np.std(v, ddof=1)) if len(v) > 1 else 0.5 * level
            out[k] = {"sem": spread / math.sqrt(2), "mdc": level + Z95 * spread, "n": int(len(v)),
                      "kind": "spread; the MDC is a threshold on the figure itself"}
    return out


# Repeat pairs a minimal detectable change must rest on before anything is flagged with it. An SEM from n
# pairs has n degrees of freedom: its 95 % interval is SEM x [sqrt(n / chi2_0.975), sqrt(n / chi2_0.025)], i.e.
# x[0.45, 31.9] from one pair, x[0.62, 2.09] from five and x[0.70, 1.75] from ten, where the upper bound first
# falls below twice the estimate: with fewer, a flag says more about the estimate than about the patient.
MIN_REPEAT_PAIRS = 10


def mdc_interval(mdc: float, n: int) -> list:
    """95 % confidence interval of an MDC estimated from ``n`` repeat pairs (chi-square on n degrees of freedom)."""
    from scipy.stats import chi2

    n = max(int(n), 1)
    return [float(mdc * math.sqrt(n / chi2.ppf(0.975, n))), float(mdc * math.sqrt(n / chi2.ppf(0.025, n)))]


def scanner_mdc(path=None, image_width: int | None = None) -> dict:
    """The scanner's own repeatability: the MDC of every index from same-day re-scans of simulated bodies.
    A clinic uses it, so labelled, until it has :data:`MIN_REPEAT_PAIRS` repeat pairs of its own. ``{}`` when
    the file is missing.

    ``analysis/scanner_mdc.json`` holds two kinds of sets: ``mdc``, the analysis's own noise on the true
    surfaces sampled as a rig sees them (``benchmarks/bench_bodies.py --write-mdc``), and ``rigs[preset]``,
    rendered and reconstructed re-scans on a simulated rig of ``image_size_px`` (``bench_rescans.py
    --write-mdc``), where the reconstruction's noise and coverage add to it. ``image_width`` (px, the rig's
    cameras; None: unknown) picks the reconstructed set of the sharpest simulated rig no sharper than it (a
    sharper rig is at least as repeatable), or the coarsest when every set is sharper; each figure takes the
    larger of that set's MDC and the true surfaces'. Without reconstructed sets, the true surfaces' alone.

    Each entry is ``{"mdc", "mdc_estimate", "sem", "n", "ci95", "source", "measured_on"}``.
    """
    import json
    from pathlib import Path

    path = Path(path) if path else Path(__file__).with_name("scanner_mdc.json")
    if not path.exists():
        return {}
    return scanner_mdc_from(json.loads(path.read_text(encoding="utf-8")), image_width)


def scanner_mdc_from(data: dict, image_width: int | None = None) -> dict:
    """:func:`scanner_mdc` of the file's content ``data`` (``{"mdc": …, "rigs": …}``)."""

    def usable(entries: dict, measured_on: str) -> dict:
        out = {}
        for k, v in (entries or {}).items():
            if (v.get("n") or 0) < MIN_REPEAT_PAIRS:
                continue
            if "mdc_estimate" not in v:  # written before the judged MDC was the interval's upper bound
                v = judged_mdc(v["mdc"], v["sem"], v["n"])
            out[k] = {**v, "source": "scanner", "measured_on": measured_on}
        return out

    out = usable(data.get("mdc"), "true surfaces")
    rigs = sorted((r for r in (data.get("rigs") or {}).values() if r.get("image_size_px")),
                  key=lambda r: r["image_size_px"][0])
    if rigs:
        fits = [r for r in rigs if image_width is not None and r["image_size_px"][0] <= image_width]
        rig = fits[-1] if fits else rigs[0]
        w, h = rig["image_size_px"]
        for k, v in usable(rig.get("mdc"), f"reconstructed re-scans, {w} x {h} px rig").items():
            if k not in out or v["mdc"] >= out[k]["mdc"]:
                out[k] = v
    return out


def usable_mdc(mdc: dict, min_pairs: int = MIN_REPEAT_PAIRS) -> dict:
    """The MDCs that rest on at least ``min_pairs`` repeat pairs (the others flag nothing)."""
    return {k: v for k, v in mdc.items() if (v.get("n") or 0) >= min_pairs}


def exceeds_mdc(change: float, mdc: float | dict | None) -> bool | None:
    """Whether ``|change|`` exceeds its minimal detectable change (None when either is unknown)."""
    if isinstance(mdc, dict):
        mdc = mdc.get("mdc")
    if mdc is None or change is None or not math.isfinite(change):
        return None
    return bool(abs(change) > mdc)


def index_changes(earlier: dict, later: dict, mdc: dict | None = None, figures=INDEX_FIGURES,
                  sides_agree: bool = True) -> dict:
    """Change of every index between two ``torso-indices/1`` reports, flagged against its MDC.

    Returns ``{figure: {"earlier", "later", "change", "mdc", "exceeds_mdc"}}`` (and ``no_verdict``, the reason,
    where a trunk landmark was placed two ways: :func:`placed_differently`, every figure but
    :data:`APEX_FIGURES` and :data:`PELVIC_FIGURES`; and ``sides``, each side's own change,
    for a figure compared side by side: :func:`_side_changes`). ``sides_agree=False``
    (the comparison's ``facing.consistent``): the two scans disagree on the patient's sides, and only the
    figures that do not depend on them are compared. A signed maximum (``X.max``) is compared side by side:
    ``earlier`` and ``later`` are then the largest values on the side that changed most (signed by the side),
    which may differ from either scan's own maximum when that maximum jumped sides.
    """
    from .indices import SIDED

    fa, fb = flatten(earlier), flatten(later)
    mixed = placed_differently(earlier, later)
    out = {}
    for k in figures:
        if not sides_agree and k.split(".")[0] in SIDED:
            continue
        pair = _figure_change(earlier, later, fa, fb, k)
        if pair is not None:
            m = (mdc or {}).get(k)
            m = m.get("mdc") if isinstance(m, dict) else m
            ch = pair[1] - pair[0]
            out[k] = {"earlier": pair[0], "later": pair[1], "change": ch, "mdc": m,
                      "exceeds_mdc": exceeds_mdc(ch, m)}
            if pair[2] is not None:
                # sides measured on neither scan are left out
                out[k]["sides"] = [{**side, "exceeds_mdc": exceeds_mdc(side["change"], m)} for side in pair[2]
                                   if side["earlier"] or side["later"]]
            if mixed and k not in APEX_FIGURES + PELVIC_FIGURES:
                names = " and ".join(n.replace("_", " ") for n in mixed)
                out[k].update(exceeds_mdc=None, no_verdict=f"no verdict: the {names} was marked on one scan and "
                                                          "found automatically on the other; mark it on both")
    return out


def flag_comparison(report: dict, mdc: dict) -> dict:
    """Add ``exceeds_mdc`` (figure -> bool) to a ``torso-comparison/1`` report, in place; returns it."""
    f = flatten(report)
    flags = {}
    for k, m in mdc.items():
        if k in f:
            v = m.get("mdc") if isinstance(m, dict) else m
            flags[k] = exceeds_mdc(f[k], v)
    report["exceeds_mdc"] = flags
    report["mdc"] = {k: (m.get("mdc") if isinstance(m, dict) else m) for k, m in mdc.items()}
    return report


def repeatability(comparison: dict) -> dict:
    """The paper's repeatability figures of one repeat pair: average normal distance and matched fraction."""
    return {"average_normal_distance_mm": comparison.get("average_normal_distance_mm"),
            "matched_fraction": comparison.get("matched_fraction")}
