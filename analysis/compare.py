"""Visit to visit: the later torso registered rigidly to the earlier one, and what changed where.

1. Robust rigid registration (:mod:`analysis.rigid`, no scale): the regions
   that really changed get zero weight and cannot drag the fit.
2. Signed normal distance of every later point to the earlier surface along
   the earlier surface's outward normal (positive: the later skin lies
   outside the earlier one); points off the earlier surface's footprint or
   farther than ``map_distance_mm`` get NaN.
3. Summaries per region, defined on the earlier torso's patient frame: upper,
   middle and lower back (thirds between the sacral point and VP), left and
   right back, chest and abdomen (the front above and below mid-trunk).
4. Growth reported separately: trunk length (VP to SP) and width change.

Frames: ``transform`` maps the later torso's (rig) frame into the earlier
one's, ``x_earlier = R @ x_later + t`` (mm).
"""

from __future__ import annotations

import numpy as np

from .config import AnalysisConfig
from .indices import analyse_torso, trunk_mask
from .landmarks import width_profile
from .rigid import coarse_alignment, register_rigid, rotation_angle_deg
from .torso import PlaneIndex, Torso

FORMAT = "torso-comparison/1"


def _stats(d: np.ndarray) -> dict:
    d = d[np.isfinite(d)]
    if len(d) == 0:
        return {"points": 0, "mean": None, "p05": None, "p95": None, "mean_abs": None, "max_abs": None}
    return {"points": int(len(d)), "mean": float(d.mean()), "p05": float(np.percentile(d, 5)),
            "p95": float(np.percentile(d, 95)), "mean_abs": float(np.abs(d).mean()),
            "max_abs": float(d[np.argmax(np.abs(d))])}


def trunk_size(analysis, torso: Torso, cfg) -> dict:
    """Trunk length (VP–SP, mm) and width (median and maximum of the trunk's width between them, mm)."""
    fr = analysis.frame
    P = fr.to_patient(torso.points)
    vp = fr.to_patient(analysis.landmarks["vertebra_prominens"])
    sp = fr.to_patient(analysis.landmarks["sacral_point"])
    zs, w = width_profile(P, cfg.indices)
    band = (zs > sp[2]) & (zs < sp[2] + 0.9 * (vp[2] - sp[2])) & np.isfinite(w)
    return {"trunk_length_mm": float(np.linalg.norm(vp - sp)), "height_mm": float(vp[2] - sp[2]),
            "width_median_mm": float(np.median(w[band])) if band.any() else None,
            "width_max_mm": float(np.max(w[band])) if band.any() else None}


def regions_of(analysis, torso: Torso, cfg) -> dict:
    """Masks (N,) of the named regions on ``torso`` (the earlier one), from its patient frame."""
    fr = analysis.frame
    P, N = fr.to_patient(torso.points), fr.rotate(torso.normals)
    vp = fr.to_patient(analysis.landmarks["vertebra_prominens"])
    sp = fr.to_patient(analysis.landmarks["sacral_point"])
    level = (P[:, 2] - sp[2]) / (vp[2] - sp[2])
    trunk = trunk_mask(P, sp[2], vp[2], cfg.indices)
    back = trunk & (N[:, 1] > 0.2)
    front = trunk & (N[:, 1] < -0.2)
    x_line = sp[0] + level * (vp[0] - sp[0])
    a, b = cfg.compare.region_bounds
    return {"back_upper": back & (level >= b), "back_middle": back & (level >= a) & (level < b),
            "back_lower": back & (level < a), "back_left": back & (P[:, 0] > x_line),
            "back_right": back & (P[:, 0] <= x_line), "chest": front & (level >= 0.5),
            "abdomen": front & (level < 0.5), "trunk": trunk}


def compare_torsos(earlier: Torso, later: Torso, cfg: AnalysisConfig | None = None, mdc: dict | None = None,
                   earlier_analysis=None, landmarks: dict | None = None, later_analysis=None,
                   later_landmarks: dict | None = None) -> dict:
    """Compare two visits; returns ``{"report": torso-comparison/1 dict, "points" (later in the earlier
    frame, (N, 3)), "normals", "deformation_mm" (N,), "regions" (name -> mask over the later points)}``.

    ``mdc``: optional minimal detectable changes (:func:`analysis.repeatability.mdc_from_comparisons`),
    figure name -> mm; every figure with one gets an ``exceeds_mdc`` flag.
    ``landmarks`` / ``later_landmarks``: clinician corrections of each torso's landmarks (its own rig frame).
    Each torso is analysed where it stands (or ``earlier_analysis`` / ``later_analysis`` are taken as they
    are), so the growth and the indices here are the very numbers of each torso's own indices report.
    """
    cfg = cfg or AnalysisConfig()
    cc = cfg.compare
    index = PlaneIndex(earlier, cfg.surface.plane_neighbours)
    reg = register_rigid(later, earlier, cfg.rigid, initial=coarse_alignment(later, earlier), fixed_index=index)
    R, t = reg["R"], reg["t"]
    moved = later.transformed(R, t)
    d, _, _, over = index.distances(moved.points, cfg.rigid.max_tangential)
    mapped = over & (np.abs(d) <= cc.map_distance_mm)
    deformation = np.where(mapped, d, np.nan)
    matched = mapped & (np.abs(d) <= cc.match_distance_mm)
    report = {
        "format": FORMAT,
        "earlier": earlier.source, "later": later.source,
        "average_normal_distance_mm": float(np.mean(np.abs(d[matched]))) if matched.any() else None,
        "matched_fraction": float(matched.mean()),
        "mapped_fraction": float(mapped.mean()),
        "signed_distance_mm": {k: v for k, v in _stats(deformation).items() if k in ("mean", "p05", "p95")},
        "transform": {"R": R.tolist(), "t": t.tolist(), "rotation_deg": rotation_angle_deg(R),
                      "maps": "later torso frame -> earlier torso frame: x_earlier = R x_later + t (mm)"},
        "registration": {"iterations": reg["iterations"], "converged": reg["converged"], "cycle": reg["cycle"],
                         "robust_sigma_mm": reg["scale_mm"], "pairs": reg["pairs"]},
        "match_distance_mm": cc.match_distance_mm,
    }
    regions = {}
    try:
        ea = earlier_analysis or analyse_torso(earlier, cfg, landmarks)
        # the later torso analysed where it stands, as its own indices were: lengths and indices do not
        # depend on the rigid placement, and a second analysis of the moved torso gave other landmarks
        # (the trunk length read 502.6 mm in the growth and 511.0 mm in the indices of one comparison)
        la = later_analysis or analyse_torso(later, cfg, later_landmarks)
        # regions: each later point takes the region of the earlier point it lies over
        masks = regions_of(ea, earlier, cfg)
        _, nb = index.tree.query(moved.points, k=1)
        regions = {k: m[nb] & mapped for k, m in masks.items()}
        report["regions"] = {k: _stats(deformation[m]) for k, m in regions.items()}
        g0, g1 = trunk_size(ea, earlier, cfg), trunk_size(la, later, cfg)
        report["growth"] = {"earlier": g0, "later": g1,
                            "change": {k: (g1[k] - g0[k]) if g0[k] is not None and g1[k] is not None else None
                                       for k in g0}}
        report["indices"] = {"earlier": _headline(ea.report), "later": _headline(la.report)}
        report["facing"] = facing_agreement(ea, la, R)
        if not report["facing"]["consistent"]:
            report.setdefault("warnings", []).append(report["facing"]["reason"])
    except ValueError as exc:
        report["regions"] = {}
        report["warnings"] = [f"regions and growth not computed: {exc}"]
    if mdc:
        from .repeatability import flag_comparison

        flag_comparison(report, mdc)
    return {"report": report, "points": moved.points, "normals": moved.normals, "deformation_mm": deformation,
            "regions": regions}


# two scans of one patient whose back directions differ by more than this (after the registration) disagree
# on the patient's sides: a same-day re-scan differs by a few degrees of sway, a visit by its placement (<10 deg)
FACING_AGREEMENT_DEG = 45.0


def facing_agreement(earlier_analysis, later_analysis, R=None) -> dict:
    """Whether two analyses agree on where the patient's back faces, and so on the patient's left and right:
    ``{"angle_deg", "consistent", ...}``. ``R`` turns the later torso's frame into the earlier's."""
    a = earlier_analysis.frame.R[1]
    b = later_analysis.frame.R[1] if R is None else np.asarray(R) @ later_analysis.frame.R[1]
    angle = float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))
    fe = earlier_analysis.report.get("frame", {}).get("facing", {})
    fl = later_analysis.report.get("frame", {}).get("facing", {})
    out = {"angle_deg": angle, "consistent": bool(angle <= FACING_AGREEMENT_DEG),
           "earlier": {k: fe.get(k) for k in ("method", "status")},
           "later": {k: fl.get(k) for k in ("method", "status")}}
    if not out["consistent"]:
        out["reason"] = (f"the two scans disagree on where the patient's back faces ({angle:.0f} deg apart after "
                         "the registration): their left and right cannot both be right, so no sided index is "
                         "compared; check the pictures")
    return out


def _headline(rep: dict) -> dict:
    return {k: rep[k] for k in ("lateral_deviation_mm", "surface_rotation_deg", "spine_lateral_deviation_mm", "midline_rotation_deg", "hump_mm",
                                "trunk_imbalance_mm", "asymmetry_mm") if k in rep}


def write_comparison(out_dir, result: dict) -> dict:
    """Write ``DIR/report.json`` and ``DIR/deformation.ply`` (later points in the earlier frame, outward
    normals, per-vertex ``deformation_mm``: NaN where the later skin is not over the earlier surface)."""
    from pathlib import Path

    from recon_engine.formats import write_json
    from recon_engine.surface import write_ply

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "deformation.ply", result["points"], result["normals"], None,
              {"deformation_mm": result["deformation_mm"].astype(np.float32)},
              comments=["torsoscan comparison: later torso in the earlier torso's frame, mm",
                        "deformation_mm: signed normal distance to the earlier surface, + outward, NaN: not over it"])
    from .jsonsafe import clean

    write_json(out / "report.json", clean(result["report"]))
    return {"report": str(out / "report.json"), "deformation": str(out / "deformation.ply")}
