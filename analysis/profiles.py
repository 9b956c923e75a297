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
- Cobb-angle estimate: the largest angle between two tangents of the spine's frontal-plane line (the
  symmetry line moved by the spine's depth and the section's rotation), the major curve's. It is an
  estimate from the surface, never a radiograph: ``docs/analysis.md`` gives its error against the
  simulator's true spine.
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


def cobb_estimate(z: np.ndarray, lateral: np.ndarray, z_sp: float, z_vp: float, step_mm: float = 4.0,
                  smooth_mm: float = 20.0) -> dict | None:
    """The major curve's Cobb-angle estimate (deg) from the spine's lateral position ``lateral(z)`` (mm, +
    towards the patient's right) between the sacral point and VP.

    The angle between the steepest tangents either side of the curve's apex: the tangent angle swings one
    way above a curve's apex and the other way below it, so its largest swing picks the major curve of a C
    or an S. Returns ``{"value_deg" (>= 0), "side" ("right"/"left": the curve's convex side),
    "apex_level", "upper_level", "lower_level" (fractions SP 0 -> VP 1)}`` or None.
    """
    profile = _trunk_profile(z, lateral, z_sp, z_vp, step_mm, smooth_mm)
    if profile is None:
        return None
    zg, x, u = profile
    theta = np.degrees(np.arctan(np.gradient(x, zg)))
    k_hi, k_lo = int(np.argmax(theta)), int(np.argmin(theta))
    a, b = sorted((k_hi, k_lo))
    # the apex: the point between the two tangents farthest from the chord joining them
    chord = x[a] + (x[b] - x[a]) * (zg[a:b + 1] - zg[a]) / max(zg[b] - zg[a], 1e-9)
    off = x[a:b + 1] - chord
    k_apex = a + int(np.argmax(np.abs(off)))
    convex_right = off[k_apex - a] > 0
    return {"value_deg": float(theta[k_hi] - theta[k_lo]), "side": "right" if convex_right else "left",
            "apex_level": float(u[k_apex]), "upper_level": float(u[b]), "lower_level": float(u[a])}


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


__all__ = ["cobb_estimate", "pelvic_figures", "sagittal_angles"]
