"""Clinical angles read from profiles of the back: the sagittal curvatures, the pelvis, a Cobb-angle estimate.

Pure functions over numpy arrays, in the patient frame (x the patient's left, y posterior, z up; mm). The
definitions follow rasterstereography (Drerup and Hierholzer; the Formetric's report):

- kyphotic angle: between the back's midline tangents at the cervicothoracic inflection (ICT, the steepest
  point above the thoracic kyphosis's crest, below VP) and the thoracolumbar inflection (ITL, the steepest
  point between the lumbar lordosis's hollow and the kyphosis's crest);
- lordotic angle: between the tangents at ITL and the lumbosacral inflection (ILS, the steepest point
  between the sacral point and the lordosis's hollow);
- pelvic obliquity: the height of the right lumbar dimple above the left (mm, and as an angle over their
  distance apart); pelvic torsion: the right dimple's sagittal surface inclination minus the left's (deg);
- Cobb-angle estimates: the angle between the end tangents of each curve of the spine's frontal-plane line
  (the symmetry line moved by the spine's depth and the section's rotation), every curve of a C or an S
  with its own side; the largest is the major curve, unless a curve of the other side is nearly as large.
  They are estimates from the surface, never radiographs: ``docs/analysis.md`` gives their error against
  the simulator's true spines.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d


def _trunk_profile(z: np.ndarray, v: np.ndarray, lo: float, hi: float, step_mm: float, smooth_mm: float):
    """``(zg, v(zg), u)``: ``v(z)`` on a regular grid over the trunk [lo, hi] (SP to VP), gaps filled linearly,
    Gaussian-smoothed (sigma mm), and each grid height as a fraction ``u`` of the trunk; None for a trunk
    under 100 mm or a profile that does not span it."""
    if not hi - lo > 100:
        return None
    z, v = np.asarray(z, float), np.asarray(v, float)
    ok = np.isfinite(z) & np.isfinite(v)
    if ok.sum() < 5:
        return None
    order = np.argsort(z[ok])
    zo, vo = z[ok][order], v[ok][order]
    zg = np.arange(lo, hi + 1e-9, step_mm)
    if len(zg) < 8 or zo[0] > lo + 0.15 * (hi - lo) or zo[-1] < hi - 0.15 * (hi - lo):
        return None  # the profile does not span the trunk: no angle can be read
    vg = np.interp(zg, zo, vo)
    return zg, gaussian_filter1d(vg, smooth_mm / step_mm, mode="nearest"), (zg - lo) / (hi - lo)


def sagittal_angles(z: np.ndarray, depth: np.ndarray, z_sp: float, z_vp: float, step_mm: float = 4.0,
                    smooth_mm: float = 15.0, margin: float = 0.05) -> dict | None:
    """Kyphotic and lordotic angles (deg) of the midline's depth profile ``depth(z)`` (mm posterior).

    ``z_sp``, ``z_vp``: the landmarks' heights (mm). Tangents are read between the landmarks, ``margin`` of
    the trunk's length away from each (their own shapes, e.g. the neck's flank, are not the back's).
    Returns ``{"kyphotic_angle_deg", "lordotic_angle_deg", "levels": {name: fraction SP 0 -> VP 1}}`` or
    None when the profile does not span the trunk.
    """
    profile = _trunk_profile(z, depth, z_sp, z_vp, step_mm, smooth_mm)
    if profile is None:
        return None
    zg, d, u = profile
    slope = np.gradient(d, zg)
    inner = (u >= margin) & (u <= 1 - margin)
    upper = inner & (u >= 0.45)
    k_kyph = np.nonzero(upper)[0][int(np.argmax(d[upper]))]
    lower = inner & (u < u[k_kyph] - 0.05)
    if lower.sum() < 3:
        return None
    k_lord = np.nonzero(lower)[0][int(np.argmin(d[lower]))]

    def steepest(sel, sign):
        idx = np.nonzero(sel)[0]
        return idx[int(np.argmax(sign * slope[idx]))] if len(idx) else None

    k_itl = steepest(inner & (u > u[k_lord]) & (u < u[k_kyph]), +1)
    k_ict = steepest(inner & (u > u[k_kyph]), -1)
    k_ils = steepest(inner & (u < u[k_lord]), -1)
    if k_itl is None or k_ict is None or k_ils is None:
        return None
    angle = np.degrees(np.arctan(slope))
    return {"kyphotic_angle_deg": float(angle[k_itl] - angle[k_ict]),
            "lordotic_angle_deg": float(angle[k_itl] - angle[k_ils]),
            "levels": {"ict": float(u[k_ict]), "kyphotic_apex": float(u[k_kyph]), "itl": float(u[k_itl]),
                       "lordotic_apex": float(u[k_lord]), "ils": float(u[k_ils])}}


def tangent_turns(theta: np.ndarray, swing_deg: float) -> list[int]:
    """Indices of the alternating extremes of a tangent-angle profile ``theta`` (deg, bottom to top), each
    differing from the next by more than ``swing_deg``: the end tangents of the curves between them.

    A wiggle smaller than ``swing_deg`` (noise on a straight stretch) makes no extreme of its own. The profile's
    ends count where the tangent keeps turning up to them (a curve that runs past the measured trunk).
    """
    theta = np.asarray(theta, float)
    n = len(theta)
    if n < 2:
        return []
    # the first move larger than the swing sets the first direction; the start's side of it is the first extreme
    moved = np.nonzero(np.abs(theta - theta[0]) > swing_deg)[0]
    if not len(moved):
        return []
    first = int(moved[0])
    rising = theta[first] > theta[0]
    turns = [int(np.argmin(theta[:first + 1]) if rising else np.argmax(theta[:first + 1]))]
    cand = first
    for i in range(first + 1, n):
        if (theta[i] > theta[cand]) if rising else (theta[i] < theta[cand]):
            cand = i
        elif abs(theta[cand] - theta[i]) > swing_deg:
            turns.append(cand)
            rising, cand = not rising, i
    turns.append(cand)
    return turns


# the region a curve is named by, from its apex's level (fraction SP 0 -> VP 1; SP about S1, VP C7, the lumbar
# vertebrae taller than the thoracic): below 0.45 (about T11) thoracolumbar or lumbar, as Lenke's
# classification groups them; up to 0.8 (about T5) thoracic; above it upper thoracic. Approximate: the levels
# of the vertebrae are not seen on the skin
CURVE_REGIONS = ((0.45, "thoracolumbar/lumbar"), (0.8, "thoracic"), (np.inf, "upper thoracic"))


def spine_curves(z: np.ndarray, lateral: np.ndarray, z_sp: float, z_vp: float, step_mm: float = 4.0,
                 smooth_mm: float = 25.0, swing_deg: float = 3.0, min_deg: float = 0.0) -> list[dict] | None:
    """Every curve of the spine's frontal line ``lateral(z)`` (mm, + towards the patient's right) between the
    sacral point and VP, with its Cobb-angle estimate (deg), bottom to top.

    The line is smoothed (Gaussian, ``smooth_mm``: about a vertebra's height) and its tangent angle read
    along the trunk; a curve lies between two successive extremes of that angle (:func:`tangent_turns`),
    which stand for its end vertebrae, and its Cobb angle is the angle between them. A curve of a C has one,
    an S two, each with its own side. Returns ``[{"value_deg", "side" ("right"/"left": the convex side),
    "region" (a name of :data:`CURVE_REGIONS`), "apex_level", "lower_level", "upper_level" (fractions SP 0
    -> VP 1)}]`` for the curves of at least ``min_deg`` (every curve the swing makes, by default: a
    listing threshold above it lets a curve near it come and go between two scans of the same back, and
    with it the largest value of its side), or None where the line does not span the trunk.
    """
    profile = _trunk_profile(z, lateral, z_sp, z_vp, step_mm, smooth_mm)
    if profile is None:
        return None
    zg, x, u = profile
    theta = np.degrees(np.arctan(np.gradient(x, zg)))
    turns = tangent_turns(theta, swing_deg)
    curves = []
    for a, b in zip(turns[:-1], turns[1:]):
        value = float(abs(theta[b] - theta[a]))
        if value < min_deg:
            continue
        # the apex: the point between the two end tangents farthest from the chord joining them
        chord = x[a] + (x[b] - x[a]) * (zg[a:b + 1] - zg[a]) / max(zg[b] - zg[a], 1e-9)
        k = a + int(np.argmax(np.abs(x[a:b + 1] - chord)))
        # the tangent turning towards the left going up bends the line out to the right: convex right
        side = "right" if theta[b] < theta[a] else "left"
        region = next(name for top, name in CURVE_REGIONS if u[k] < top)
        curves.append({"value_deg": value, "side": side, "region": region, "apex_level": float(u[k]),
                       "lower_level": float(u[a]), "upper_level": float(u[b])})
    return curves


def cobb_estimate(z: np.ndarray, lateral: np.ndarray, z_sp: float, z_vp: float, step_mm: float = 4.0,
                  smooth_mm: float = 25.0, swing_deg: float = 3.0, min_deg: float = 0.0,
                  double_major_deg: float = 5.0) -> dict | None:
    """The Cobb-angle estimates (deg) of the spine's curves (:func:`spine_curves`) and which is the major one.

    Returns ``{"curves": [...], "major": the largest curve or None, "double_major": True where a curve of the
    other side is within ``double_major_deg`` of it (two curves nearly alike: which one is larger is within
    the estimate's error, so neither is called the major one alone), "right", "left": each side's largest
    curve or None}``, or None where the line does not span the trunk.
    """
    curves = spine_curves(z, lateral, z_sp, z_vp, step_mm, smooth_mm, swing_deg, min_deg)
    if curves is None:
        return None
    major = max(curves, key=lambda c: c["value_deg"]) if curves else None
    sides = {side: max((c for c in curves if c["side"] == side), key=lambda c: c["value_deg"], default=None)
             for side in ("right", "left")}
    other = sides["left" if major and major["side"] == "right" else "right"] if major else None
    double = bool(other and major["value_deg"] - other["value_deg"] < double_major_deg)
    return {"curves": curves, "major": major, "double_major": double, **sides}


def pelvic_figures(left: np.ndarray, right: np.ndarray, incl_left_deg: float, incl_right_deg: float) -> dict:
    """Pelvic obliquity and torsion from the lumbar dimples (patient frame, mm) and the back's sagittal
    inclination at each (deg, + when the surface faces upwards).

    ``pelvic_obliquity_mm``: the right dimple's height above the left's (+: the right side of the pelvis
    higher); ``pelvic_obliquity_deg``: the same as an angle over the dimples' distance apart;
    ``pelvic_torsion_deg``: right minus left inclination (a pelvis twisted about the transverse axis turns
    one iliac crest's surface upwards and the other's downwards).
    """
    dz = float(right[2] - left[2])
    dx = float(abs(left[0] - right[0]))
    return {"pelvic_obliquity_mm": dz, "pelvic_obliquity_deg": float(np.degrees(np.arctan2(dz, max(dx, 1e-9)))),
            "pelvic_torsion_deg": float(incl_right_deg - incl_left_deg), "dimple_distance_mm": dx}


__all__ = ["CURVE_REGIONS", "cobb_estimate", "pelvic_figures", "sagittal_angles", "spine_curves", "tangent_turns"]
