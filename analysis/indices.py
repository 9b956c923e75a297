"""Clinical surface indices of one torso, in the style of rasterstereography (Formetric) and ISIS.

Pipeline (all in the patient frame of :mod:`analysis.frame`):

1. posterior direction detected (or given), mid-sagittal plane from registering
   the torso to its own mirror image: the patient frame;
2. the back's depth map (:mod:`analysis.backsurface`);
3. VP, SP and the lumbar dimples (:mod:`analysis.landmarks`), or the
   clinician's corrections;
4. horizontal sections between VP and SP; in each, the symmetry point (the
   line of symmetry) and its lateral deviation, the surface rotation (the
   whole transverse section's), the skin normal's rotation at the symmetry
   line (rasterstereography's figure), the spine midline estimate, the hump;
5. summaries per region and overall, trunk imbalance, whole-torso asymmetry;
   the kyphotic and lordotic angles, the pelvis's obliquity and torsion at
   the dimples and a Cobb-angle estimate (:mod:`analysis.profiles`).

Signs: lateral values positive towards the patient's right; surface rotation
positive when the back's right side comes backwards (the vertebral bodies
turned to the right, a right rib hump); hump positive when the right side is
higher (more posterior).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .backsurface import DepthMap, back_points, central_extent, depth_map, prominence_difference, slope_at
from .config import AnalysisConfig, IndicesConfig, RigidConfig
from .frame import PatientFrame, detect_posterior, frame_from_posterior, symmetry_plane
from .landmarks import broad_slope, detect_landmarks, find_dimples, marked_point, sagittal_inclination
from .profiles import cobb_estimate, pelvic_figures, sagittal_angles
from .torso import PlaneIndex, Torso

FORMAT = "torso-indices/1"
CORE_LANDMARKS = ("vertebra_prominens", "sacral_point")  # the trunk's ends: every section rests on them
DIMPLES = ("dimple_left", "dimple_right")  # the lumbar dimples: the pelvic figures rest on them
LANDMARKS = CORE_LANDMARKS + DIMPLES
_AUTO = {"vertebra_prominens": "vp", "sacral_point": "sp", "dimple_left": "dimple", "dimple_right": "dimple"}


@dataclass
class TorsoAnalysis:
    """What :func:`analyse_torso` found: the report plus what pictures and comparisons need."""

    report: dict
    frame: PatientFrame
    depth_map: DepthMap
    landmarks: dict  # name -> rig-frame point (mm)
    asymmetry_mm: np.ndarray  # (N,) per torso point, NaN outside the trunk or off the mirror image
    sections: list = field(default_factory=list)


@dataclass(frozen=True)
class StoredAnalysis:
    """What a comparison needs of a torso's analysis, read back from its torso-indices report: the report, the
    patient frame and the landmarks (rig frame, mm; NaN where the report has none)."""

    report: dict
    frame: PatientFrame
    landmarks: dict


def analysis_from_report(report: dict | None) -> StoredAnalysis | None:
    """The analysis a stored torso-indices report (:func:`analyse_torso`'s ``report``, as JSON) describes, or
    None when the report lacks the frame or a core landmark's entry (an older or failed analysis).

    The numbers are the report's own, so a comparison built on it shows the very figures the torso's own page
    shows, without analysing the torso again (two thirds of a comparison's time).
    """
    if not report or report.get("format") != FORMAT or "frame" not in report:
        return None
    marks = report.get("landmarks") or {}
    if any(k not in marks for k in CORE_LANDMARKS):
        return None
    landmarks = {k: np.asarray(v["position_mm"] if v.get("position_mm") is not None else [np.nan] * 3, float)
                 for k, v in marks.items()}
    return StoredAnalysis(report, PatientFrame.from_dict(report["frame"]), landmarks)


def signed_max(v) -> float:
    """The value of largest magnitude, with its sign (NaN-safe)."""
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(v[np.argmax(np.abs(v))]) if len(v) else float("nan")


def rms(v) -> float:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if len(v) else float("nan")


def _summary(sections, key, within=None):
    """RMS and signed maximum over the sections (the spec's), and each side's largest value with its level.

    ``within``: the indices of the sections (of ``sections``, all of them by default) the figures are over, a
    region's. The RMS is over the levels: an unread section (NaN) between read ones counts with the value
    interpolated in height from its neighbours (:func:`fill_between`), so that two scans of one back that could
    not read the same few levels give the same RMS (a re-scan that missed three sections at the thoracic
    apex read its RMS 0.23 deg lower). The maximum and the sides are read values only.

    ``right`` / ``left``: the largest value towards the patient's right (positive) and left (negative), as a
    size (>= 0) with its level (fraction SP -> VP) and height above SP (mm); None where no section leans
    that way. An S-curve has one of each; a signed maximum alone jumps sides when the two are close.
    """
    within = np.arange(len(sections)) if within is None else np.asarray(within, int)
    vals = np.array([s[key] for s in sections], float)
    filled = fill_between([s["z_mm"] for s in sections], vals)
    sel = [sections[i] for i in within]
    return {"rms": rms(filled[within]), "max": signed_max(vals[within]), **_sides(sel, key)}


def fill_between(z, v) -> np.ndarray:
    """``v`` (one value per height ``z``, mm, increasing) with every NaN that lies between two finite values
    replaced by the linear interpolation between them in height; NaNs before the first and after the last finite
    value stay. A new array: ``v`` is not changed."""
    z, v = np.asarray(z, float), np.array(v, float)
    ok = np.isfinite(v)
    if ok.sum() < 2:
        return v
    k = np.nonzero(ok)[0]
    inner = ~ok & (np.arange(len(v)) > k[0]) & (np.arange(len(v)) < k[-1])
    v[inner] = np.interp(z[inner], z[ok], v[ok])
    return v


def unread_runs(v) -> list:
    """``[(first, last), ...]``: the index ranges (inclusive) of the runs of NaN in ``v``."""
    bad = ~np.isfinite(np.asarray(v, float))
    edges = np.diff(np.r_[0, bad.astype(int), 0])
    return list(zip(np.flatnonzero(edges == 1).tolist(), (np.flatnonzero(edges == -1) - 1).tolist()))


def _cobb_sides(cobb: dict | None, z_sp: float, z_vp: float) -> dict:
    """``{"max", "right", "left"}`` of the Cobb estimates (:func:`analysis.profiles.cobb_estimate`) in the
    shape of :func:`_summary`: the major curve signed (+ convex right), each side's largest with its level."""
    if not cobb:
        return {"max": None, "right": None, "left": None}
    major = cobb["major"]
    out = {"max": (major["value_deg"] * (1.0 if major["side"] == "right" else -1.0)) if major else None}
    for side in ("right", "left"):
        c = cobb[side]
        out[side] = ({"size": c["value_deg"], "level": c["apex_level"],
                      "height_mm": c["apex_level"] * (z_vp - z_sp)} if c else None)
    return out


def _sides(sections, key):
    """``{"right", "left"}``: each side's largest value of ``key`` over the sections, with its level (see
    :func:`_summary`)."""
    vals = np.array([s[key] for s in sections], float)
    out = {}
    z_sp = sections[0]["z_mm"] - sections[0]["level"] * (sections[1]["z_mm"] - sections[0]["z_mm"]) / \
        max(sections[1]["level"] - sections[0]["level"], 1e-9) if len(sections) > 1 else sections[0]["z_mm"]
    for side, sign in (("right", 1.0), ("left", -1.0)):
        v = np.where(np.isfinite(vals), sign * vals, -np.inf)
        k = int(np.argmax(v)) if len(v) else 0
        out[side] = ({"size": float(v[k]), "level": sections[k]["level"], "height_mm": sections[k]["z_mm"] - z_sp}
                     if len(v) and v[k] > 0 else None)
    return out


def smooth_along(z: np.ndarray, v: np.ndarray, sigma_mm: float) -> np.ndarray:
    """``v`` (one value per height ``z``, mm) smoothed by a Gaussian of ``sigma_mm`` along the height; a NaN value
    stays NaN and takes no part in its neighbours'. ``sigma_mm`` <= 0 returns a copy."""
    z, v = np.asarray(z, float), np.array(v, float)
    ok = np.isfinite(v)
    if sigma_mm <= 0 or not ok.any():
        return v
    w = np.exp(-0.5 * ((z[:, None] - z[None, ok]) / sigma_mm) ** 2)
    out = np.full_like(v, np.nan)
    out[ok] = (w[ok] @ v[ok]) / w[ok].sum(axis=1)
    return out


def trunk_mask(P: np.ndarray, z_lo: float, z_hi: float, cfg: IndicesConfig, step_mm: float | None = None) -> np.ndarray:
    """Points (patient frame) of the trunk between two heights, arms cut off at the gaps beside the trunk."""
    step_mm = step_mm or max(4.0, 2.0 * cfg.grid_mm)
    mask = np.zeros(len(P), bool)
    band = (P[:, 2] >= z_lo) & (P[:, 2] <= z_hi)
    idx = np.floor((P[:, 2] - z_lo) / step_mm).astype(int)
    for k in np.unique(idx[band]):
        sel = np.nonzero(band & (idx == k))[0]
        a, b = central_extent(P[sel, 0], cfg.gap_mm, 0.0)
        mask[sel[(P[sel, 0] >= a) & (P[sel, 0] <= b)]] = True
    return mask


def section_symmetry(Q: np.ndarray, x0: float, normals: np.ndarray | None = None, iterations: int = 30,
                     min_agreement: float = 0.0, agree_mm: float = 5.0) -> tuple[float, float]:
    """Axial rotation (deg) of one transverse section of the trunk, from its mirror symmetry, and the share of
    the section's points whose registered mirror image lies within ``agree_mm`` (mm) of the outline; the
    rotation is NaN where that share is below ``min_agreement``, or where the section reaches less than half as
    far on one side of ``x0`` as on the other.

    ``Q``: (n, 2) patient-frame ``x`` (left) and ``y`` (posterior) of the section's points, back and front, arms
    cut off; ``normals``: their outward normals' horizontal parts (n, 2). The section reflected about ``x = x0``
    is registered rigidly to itself (2D, point-to-line against the nearest point's tangent, so points slide
    along the outline; pairs beyond three times their median distance dropped); the composed map is the
    reflection about the section's own axis of symmetry, and the angle of that axis from the posterior
    direction is the section's rotation, positive when the right back comes backwards. A hump on one side of
    the back is a small part of the whole outline and tilts this axis much less than it tilts the skin at the
    midline. Without normals the pairs are point to point (slower to slide, biased towards the start).
    """
    from scipy.spatial import cKDTree

    Q = np.asarray(Q, float)
    nan = (float("nan"), float("nan"))
    if len(Q) < 60 or not np.isfinite(x0):
        return nan
    # a section seen on one side of the symmetry point only (the run holding the midline cut at a hole beside
    # it) is no trunk's outline: the free translation slides the mirror image onto that half's own axis, which
    # then read 85 deg on a rendered re-scan (agreement 0.84)
    reach = (x0 - Q[:, 0].min(), Q[:, 0].max() - x0)
    if min(reach) < 0.5 * max(reach):
        return nan
    if normals is not None:
        Nn = np.asarray(normals, float)
        ln = np.linalg.norm(Nn, axis=1)
        ok = ln > 0.3  # points whose normal is mostly horizontal: the outline is well defined there
        Q, Nn = Q[ok], Nn[ok] / ln[ok, None]
        if len(Q) < 60:
            return nan
    M = np.diag([-1.0, 1.0])
    R, t = np.eye(2), np.array([2.0 * x0, 0.0])
    tree = cKDTree(Q)
    QM = Q @ M.T
    for _ in range(iterations):
        S = QM @ R.T + t
        d, j = tree.query(S)
        keep = d <= max(3.0 * np.median(d), 2.0)
        if keep.sum() < 30:
            return nan
        A, B = S[keep], Q[j[keep]]
        if normals is None:
            ma, mb = A.mean(axis=0), B.mean(axis=0)
            U, _, Vt = np.linalg.svd((A - ma).T @ (B - mb))
            dR = Vt.T @ U.T
            if np.linalg.det(dR) < 0:
                Vt[-1] *= -1
                dR = Vt.T @ U.T
            dt = mb - dR @ ma
        else:
            n = Nn[j[keep]]
            c = A.mean(axis=0)
            Ac = A - c
            J = np.column_stack([-Ac[:, 1] * n[:, 0] + Ac[:, 0] * n[:, 1], n[:, 0], n[:, 1]])
            r = np.einsum("ij,ij->i", B - A, n)
            x = np.linalg.lstsq(J, r, rcond=None)[0]
            ca, sa = np.cos(x[0]), np.sin(x[0])
            dR = np.array([[ca, -sa], [sa, ca]])
            dt = c + x[1:] - dR @ c
        R, t = dR @ R, dR @ t + dt
        if normals is not None and abs(x[0]) < 1e-7 and np.hypot(x[1], x[2]) < 1e-5:
            break
    # R·M is the reflection about the axis at angle 90° + phi/2 from +x (x left, y posterior): phi/2 from the
    # posterior direction, positive towards +x; the right (-x) back coming backwards turns it towards -x
    phi = np.degrees(np.arctan2(R[1, 0], R[0, 0]))
    agreement = float(np.mean(tree.query(QM @ R.T + t)[0] <= agree_mm))
    return (float(-phi / 2) if agreement >= min_agreement else float("nan")), agreement


def initial_frame(torso: Torso, ic: IndicesConfig, landmarks: dict | None = None) -> dict:
    """The patient frame before the yaw is refined, and the landmarks found in it.

    The facing from the shape (a clinician's mark or the rig only choosing which end of its depth axis is the
    back), the yaw and origin across from the whole torso's mirror plane. Returns ``{"ic" (the config with
    cells and smoothing grown for a sparse cloud), "frame", "P", "N" (points and normals, patient frame, mm),
    "dmap", "back", "auto" (landmarks found), "facing", "rc", "index"}``.
    """
    from .torso import spacings

    # clustered samples (a sparse reconstruction's features bunch on the pattern's blobs) are sparser than
    # their nearest-neighbour distance says: with cells that small the depth map was mostly holes and the
    # midline was found on a few rows only (tiny preset: VP 48 mm low, SP 300 mm high)
    nearest, sampling = spacings(torso.points)
    spacing = max(nearest, 0.9 * sampling)
    if ic.smooth_mm < 1.5 * spacing or ic.grid_mm < 1.0 * spacing:
        # a sparse cloud (a reduced rig): cells and smoothing grow with the point spacing
        ic = replace(ic, grid_mm=max(ic.grid_mm, 1.0 * spacing), smooth_mm=max(ic.smooth_mm, 1.5 * spacing),
                     gap_mm=max(ic.gap_mm, 4.0 * spacing))
    post, facing = detect_posterior(torso.points, ic.facing, _clinician_facing(torso, landmarks) or torso.patient)
    c = np.median(torso.points, axis=0)
    frame0 = frame_from_posterior(post, [c[0], c[1], 0.0])
    rc = RigidConfig(initial_distance_mm=60.0, min_distance_mm=3.0, sample=8000)
    index = PlaneIndex(torso)
    # the mid-sagittal plane of the whole torso sets the yaw and the origin across
    try:
        sym = symmetry_plane(torso, frame0, rc, index=index)
        frame = sym["frame"]
        if abs(np.degrees(np.arccos(np.clip(frame.R[1] @ frame0.R[1], -1, 1)))) > 20:
            frame = frame0
    except ValueError:
        frame = frame0
    frame.origin[2] = 0.0
    return {"ic": ic, "frame": frame, **seen_in_frame(torso, frame, ic), "facing": facing, "rc": rc, "index": index}


def seen_in_frame(torso: Torso, frame: PatientFrame, ic: IndicesConfig) -> dict:
    """What the analysis reads in one patient frame: ``{"P", "N"}`` (points and normals, patient frame, mm),
    ``"dmap"`` (the back's depth map), ``"back"`` (the back's points, bool) and ``"auto"`` (landmarks found)."""
    P, N = frame.to_patient(torso.points), frame.rotate(torso.normals)
    dmap = depth_map(P, N, ic)
    back = back_points(P, N, ic)
    return {"P": P, "N": N, "dmap": dmap, "back": back, "auto": detect_landmarks(P, back, dmap, ic)}


def band_yaw_frame(torso: Torso, start: dict, bands, max_turn_deg: float = 10.0):
    """The patient frame with its yaw from the mirror plane of the trunk within height bands (``[(z_lo, z_hi),
    ...]``, patient frame, mm; arms cut off), starting from :func:`initial_frame`'s ``start``; None where the
    bands hold 500 points or fewer, the registration fails, or the plane turns by more than ``max_turn_deg``
    from the start's."""
    band = np.zeros(len(start["P"]), bool)
    for z_lo, z_hi in bands:
        band |= trunk_mask(start["P"], z_lo, z_hi, start["ic"])
    if band.sum() <= 500:
        return None
    try:
        f = symmetry_plane(torso, start["frame"], start["rc"], mask=band, index=start["index"])["frame"]
    except ValueError:
        return None
    if np.degrees(np.arccos(np.clip(f.R[1] @ start["frame"].R[1], -1, 1))) >= max_turn_deg:
        return None
    f.origin[2] = 0.0
    return f


def analyse_torso(torso: Torso, cfg: AnalysisConfig | None = None, landmarks: dict | None = None) -> TorsoAnalysis:
    """Indices of one torso (rig frame, +Z up) with the frame, depth map, landmarks and asymmetry map.

    ``landmarks``: optional clinician corrections, ``{"vertebra_prominens": [x, y, z],
    "sacral_point": [x, y, z]}`` in the torso's (rig) frame, mm; either may be left out.
    """
    cfg = cfg or AnalysisConfig()
    start = initial_frame(torso, cfg.indices, landmarks)
    ic, facing, frame, P, N, rc = (start[k] for k in ("ic", "facing", "frame", "P", "N", "rc"))
    dmap, back, auto = start["dmap"], start["back"], start["auto"]
    # the yaw again, from the pelvis only (the trunk around SP): a scoliotic curve turns the sections above it
    # and would tilt a whole-trunk mirror plane towards its own rotation. The shoulders are no reference either:
    # the band below VP carries the upper thoracic curve's rotation (it read the yaw 1.7 deg off the pelvis's
    # on average, 2.8 at most, on tuning seed 100's rendered re-scans) and moves with VP's height (up to 0.7
    # deg for 12 mm); the pelvis band read the simulated pelvis's yaw within 0.05 deg and moved by at most
    # 0.4 deg for SP moved by ±12 mm (benchmarks/bench_yaw.py)
    z_sp, z_vp = auto["sacral_point"][2], auto["vertebra_prominens"][2]
    if np.isfinite(z_sp) and np.isfinite(z_vp) and z_vp > z_sp + 100:
        L = z_vp - z_sp
        f2 = band_yaw_frame(torso, start, [(z_sp - ic.yaw_band * L, z_sp + ic.yaw_band * L)])
        if f2 is not None:
            frame = f2
            seen = seen_in_frame(torso, frame, ic)
            P, N, dmap, back, auto = (seen[k] for k in ("P", "N", "dmap", "back", "auto"))
    for k in landmarks or {}:
        if k not in LANDMARKS:
            raise ValueError(f"unknown landmark {k!r}: choose from {', '.join(LANDMARKS)}")
    lm = {k: auto[k] for k in CORE_LANDMARKS}
    source = {k: "auto" for k in LANDMARKS}

    def corrected(names):
        for k in names:
            v = (landmarks or {}).get(k)
            if v is None:
                continue
            lm[k] = marked_point(dmap, frame.to_patient(np.asarray(v, float).reshape(3)))
            source[k] = "clinician"

    corrected(CORE_LANDMARKS)
    vp, sp = lm["vertebra_prominens"], lm["sacral_point"]
    if not vp[2] > sp[2] + 100:
        raise ValueError(f"vertebra prominens ({vp[2]:.0f} mm) not well above the sacral point ({sp[2]:.0f} mm)")
    length = float(vp[2] - sp[2])
    # the dimples are searched above the sacral point in use (the clinician's, when corrected)
    auto.update(find_dimples(dmap, sp[2], length, auto["midline"], sp[0]))
    lm.update({k: auto[k] for k in DIMPLES})
    corrected(DIMPLES)

    sections = []
    mz, mx, _ = auto["midline"]
    okm = np.isfinite(mx)
    # the line of symmetry smoothed along the height (Gaussian, sigma ic.line_smooth_mm), as rasterstereography does
    mz, mx = mz[okm], mx[okm]
    mx_s = smooth_along(mz, mx, ic.line_smooth_mm)
    # the lateral deviation's reference: the straight line joining the symmetry line's own points at the SP and
    # VP heights. The landmarks' x would carry their own scatter into every section (a clicked SP 2 mm off, an
    # automatic one a few mm the other way); on the tuning bodies (seed 100) this cut the lateral deviation
    # maximum's re-scan change from 1.90 to 1.32 mm (true surfaces) and its error from 1.60 to 1.39 mm mean abs
    x_ref = (float(np.interp(sp[2], mz, mx_s)), float(np.interp(vp[2], mz, mx_s)))
    for s in np.arange(ic.end_margin, 1 - ic.end_margin + 1e-9, ic.section_step):
        z = sp[2] + s * length
        x_line = x_ref[0] + s * (x_ref[1] - x_ref[0])
        row = dmap.row(z)
        x0 = float(np.interp(z, mz, mx_s))
        misfit = float(np.interp(z, mz, mx) - x0)
        if not np.isfinite(x0):
            continue
        m = slope_at(dmap.x, row, x0, ic.rotation_window_mm)
        rot = float(np.degrees(np.arctan(-m)))  # right side higher -> positive
        sec = trunk_mask(P, z - ic.section_half_height_mm, z + ic.section_half_height_mm, ic)
        # NaN where not mirror-symmetric enough to read (an arm touching the trunk, a flank unseen)
        sec_rot, agreement = section_symmetry(P[sec, :2], x0, N[sec, :2], ic.section_iterations,
                                              ic.section_min_agreement)
        hump, span = prominence_difference(dmap.x, row, x0, ic.hump_range_mm)
        sections.append({
            "level": round(float(s), 4), "z_mm": float(z),
            "symmetry_point_mm": float(x0), "symmetry_residual_mm": float(misfit),
            # the lateral deviation: the line of symmetry's, measured on the skin
            "lateral_deviation_mm": float(-(x0 - x_line)),
            # Formetric-style spine midline: the symmetry line moved by a model depth of the spine (below)
            "spine_lateral_deviation_mm": float("nan"),
            # the whole transverse section's rotation (a rib hump tilts it far less than the midline skin)
            "surface_rotation_deg": sec_rot,
            "section_agreement": agreement,  # share of the section's mirror image within 5 mm of its outline
            # rasterstereography's surface rotation: the skin normal at the symmetry line
            "midline_rotation_deg": rot,
            "hump_mm": hump,
            "hump_angle_deg": float(np.degrees(np.arctan2(hump, span))) if np.isfinite(hump) else float("nan"),
            "depth_mm": float(np.interp(x0, dmap.x, row)),
        })
    if len(sections) < 3:
        raise ValueError("too few horizontal sections of the back could be read")
    # the spine midline: the symmetry line moved towards the patient's front by the spine's model depth, turned by
    # the section's rotation. A short run of unread sections (under the span at which the surface rotation is
    # withheld) takes the rotation interpolated from the read sections at its ends: the skin's rotation at the
    # midline read 2-3 deg more than the section's beside an arm (seed 300, body 7), and a re-scan that read
    # other sections moved the spine line by 2 mm there. A longer run (forearms across the chest) keeps the
    # midline's rotation, whose shape follows the curve through its apex where a straight line would cut it off
    # (interpolated there too, the Cobb estimates of seed 200's and 300's crossed bodies erred 0.2 deg more)
    mid_rot = np.array([x["midline_rotation_deg"] for x in sections])
    spine_rot = mid_rot
    if ic.spine_rotation == "section":
        sec_rot = np.array([x["surface_rotation_deg"] for x in sections])
        spine_rot = fill_between([x["z_mm"] for x in sections], sec_rot)
        levels = np.array([x["level"] for x in sections])
        for lo, hi in unread_runs(sec_rot):
            if levels[hi] - levels[lo] >= ic.unread_apex_min_span - 1e-6:
                spine_rot[lo:hi + 1] = mid_rot[lo:hi + 1]
        spine_rot = np.where(np.isfinite(spine_rot), spine_rot, mid_rot)  # beyond the first and last read ones
    for x, r in zip(sections, spine_rot):
        x["spine_lateral_deviation_mm"] = float(x["lateral_deviation_mm"] + ic.spine_depth_mm * np.sin(np.radians(r)))
    if ic.rotation_smooth_mm > 0:  # see IndicesConfig.rotation_smooth_mm
        zs = [s["z_mm"] for s in sections]
        for key in ("surface_rotation_deg", "midline_rotation_deg"):
            for s, v in zip(sections, smooth_along(zs, [s[key] for s in sections], ic.rotation_smooth_mm)):
                s[key.replace("_deg", "_unsmoothed_deg")] = s[key]
                s[key] = float(v)

    # whole-torso asymmetry: the trunk between SP and VP registered to its own mirror image
    zb = ic.mirror_band * length
    mask = trunk_mask(P, sp[2] - zb, vp[2] + zb, ic)
    asym = np.full(len(torso), np.nan)
    asym_fig = {"mean_abs_mm": float("nan"), "rms_mm": float("nan"), "p95_abs_mm": float("nan")}
    try:
        sub = Torso(torso.points[mask], torso.normals[mask])
        res = symmetry_plane(sub, frame, rc)
        # each trunk point against the mirror image (registered): + where this side stands out
        from .frame import mirror

        m_img = mirror(sub, frame).transformed(res["R"], res["t"])
        d, _, _, over = PlaneIndex(m_img).distances(sub.points, rc.max_tangential)
        d = np.where(over, d, np.nan)
        asym[np.nonzero(mask)[0]] = d
        a = np.abs(d[np.isfinite(d)])
        asym_fig = {"mean_abs_mm": float(a.mean()), "rms_mm": float(np.sqrt(np.mean(a ** 2))),
                    "p95_abs_mm": float(np.percentile(a, 95)), "points": int(len(a))}
    except ValueError:
        pass

    regions = {}
    for name, lo, hi in ic.regions:
        within = [i for i, s in enumerate(sections) if lo <= s["level"] < hi or (hi >= 1.0 and s["level"] <= hi)]
        if within:
            regions[name] = {"levels": [lo, hi],
                             **{key: _summary(sections, key, within) for key in (
                                 "lateral_deviation_mm", "spine_lateral_deviation_mm", "surface_rotation_deg",
                                 "midline_rotation_deg")},
                             "hump_mm": signed_max([sections[i]["hump_mm"] for i in within])}
    def apex_of(key):
        return max(sections, key=lambda s: abs(s[key]) if np.isfinite(s[key]) else -1)

    sagittal = sagittal_angles(mz, auto["midline"][2][okm], sp[2], vp[2])
    cobb = cobb_estimate([s["z_mm"] for s in sections], [s["spine_lateral_deviation_mm"] for s in sections],
                         sp[2], vp[2])
    if np.all(np.isfinite(lm["dimple_left"])) and np.all(np.isfinite(lm["dimple_right"])):
        slope = broad_slope(dmap)
        pelvis = pelvic_figures(lm["dimple_left"], lm["dimple_right"],
                                sagittal_inclination(dmap, lm["dimple_left"][0], lm["dimple_left"][2], slope),
                                sagittal_inclination(dmap, lm["dimple_right"][0], lm["dimple_right"][2], slope))
    else:
        pelvis = {k: None for k in PELVIC}
    apex, spine_apex = apex_of("lateral_deviation_mm"), apex_of("spine_lateral_deviation_mm")
    rot_apex, mid_apex = apex_of("surface_rotation_deg"), apex_of("midline_rotation_deg")
    lm_rig = {k: frame.to_rig(v) for k, v in lm.items()}
    hump_sides = {"max": signed_max([s["hump_mm"] for s in sections]), **_sides(sections, "hump_mm")}
    angle_sides = {"max": signed_max([s["hump_angle_deg"] for s in sections]), **_sides(sections, "hump_angle_deg")}
    report = {
        "format": FORMAT,
        "source": torso.source,
        "lateral_deviation_mm": _summary(sections, "lateral_deviation_mm"),
        "surface_rotation_deg": _summary(sections, "surface_rotation_deg"),
        "spine_lateral_deviation_mm": _summary(sections, "spine_lateral_deviation_mm"),
        "midline_rotation_deg": _summary(sections, "midline_rotation_deg"),
        "hump_mm": hump_sides["max"],
        "hump_angle_deg": angle_sides["max"],
        # the hump on each side: an S curve's two humps can be nearly equal, and its signed maximum jumps sides
        "hump": hump_sides,
        "hump_angle": angle_sides,
        "trunk_imbalance_mm": float(-(vp[0] - sp[0])),
        "trunk_inclination_mm": float(vp[1] - sp[1]),
        "trunk_length_mm": float(np.linalg.norm(vp - sp)),
        "asymmetry_mm": asym_fig["mean_abs_mm"],
        "asymmetry": asym_fig,
        "kyphotic_angle_deg": sagittal["kyphotic_angle_deg"] if sagittal else None,
        "lordotic_angle_deg": sagittal["lordotic_angle_deg"] if sagittal else None,
        "sagittal_levels": sagittal["levels"] if sagittal else None,
        # as the other sided figures: each side's largest curve (the size, its apex's level and height above
        # SP), and the major curve's signed (+ convex to the patient's right)
        "cobb_estimate_deg": _cobb_sides(cobb, sp[2], vp[2]),
        "cobb_estimate": {**cobb, "note": COBB_NOTE} if cobb else None,
        "pelvic_obliquity_mm": pelvis["pelvic_obliquity_mm"],
        "pelvic_obliquity_deg": pelvis["pelvic_obliquity_deg"],
        "pelvic_torsion_deg": pelvis["pelvic_torsion_deg"],
        "apex": {"lateral_deviation": {"level": apex["level"], "z_mm": apex["z_mm"],
                                       "value_mm": apex["lateral_deviation_mm"]},
                 "spine_lateral_deviation": {"level": spine_apex["level"], "z_mm": spine_apex["z_mm"],
                                             "value_mm": spine_apex["spine_lateral_deviation_mm"]},
                 "surface_rotation": {"level": rot_apex["level"], "z_mm": rot_apex["z_mm"],
                                      "value_deg": rot_apex["surface_rotation_deg"]},
                 "midline_rotation": {"level": mid_apex["level"], "z_mm": mid_apex["z_mm"],
                                      "value_deg": mid_apex["midline_rotation_deg"]}},
        "landmarks": {k: {"position_mm": lm_rig[k].tolist() if np.all(np.isfinite(lm_rig[k])) else None,
                          "source": source[k],
                          "method": auto[_AUTO[k] + "_method"] if source[k] == "auto" else "clinician",
                          "confidence": auto[_AUTO[k] + "_confidence"] if source[k] == "auto" else "clinician",
                          "evidence_mm": auto[_AUTO[k] + "_evidence_mm"]} for k in LANDMARKS},
        "frame": {**frame.to_dict(), "facing": facing,
                  "convention": "x left, y posterior, z up; reported lateral values positive towards the "
                                "patient's right, rotation positive when the right back comes backwards"},
        "regions": regions,
        "sections": sections,
        "units": {"lengths": "mm", "angles": "deg"},
    }
    if facing.get("status") == "uncertain":
        withhold(report, f"not measurable on this scan: the patient's facing is uncertain ({facing.get('reason')}); "
                         "mark the vertebra prominens on the back to settle it")
    else:
        unsure = [k for k in CORE_LANDMARKS if source[k] == "auto" and auto[_AUTO[k] + "_confidence"] != "high"]
        if unsure:
            names = " and ".join(k.replace("_", " ") for k in unsure)
            withhold(report, f"not measurable on this scan: the {names} could not be found with confidence "
                             f"({', '.join(auto[_AUTO[k] + '_method'] for k in unsure)}); mark the landmark",
                     LANDMARKED, landmarks=unsure)
        unsure = [k for k in DIMPLES if source[k] == "auto" and auto["dimple_confidence"] != "high"]
        if unsure:
            withhold(report, f"the pelvic figures are not measurable on this scan: the lumbar dimples could not be "
                             f"found with confidence ({auto['dimple_method']}); mark them", PELVIC, landmarks=unsure)
        unread = unread_apex_levels(sections, min_span=ic.unread_apex_min_span)
        if unread and report.get("surface_rotation_deg", {}).get("max") is not None:
            withhold(report, "the surface rotation is not measurable on this scan: the trunk's horizontal sections "
                             "could not be read where the back turns most (levels "
                             + ", ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in unread) + " of SP to VP): their outline "
                             "there is not the trunk's alone (arms held across the chest or pressed against the "
                             "flanks, or a flank unseen); scan again with the arms hanging free",
                     ("surface_rotation_deg",), in_regions=True)
    return TorsoAnalysis(report, frame, dmap, lm_rig, asym, sections)


def unread_apex_levels(sections: list, min_deg: float = 2.0, min_span: float = 0.0) -> list:
    """The runs of unread sections (``[(first level, last level), ...]``, spanning at least ``min_span`` of
    SP-VP) that hold a side's apex as the back's midline shows it: the section where the midline skin rotation is
    largest towards that side (at least ``min_deg``) has no surface rotation. There the surface rotation's
    maximum would be another level's, or the other side's curve, and nothing on the scan tells a reader so."""
    rot = np.array([s["surface_rotation_deg"] for s in sections], float)
    mid = np.array([s["midline_rotation_deg"] for s in sections], float)
    levels = np.array([s["level"] for s in sections], float)
    runs = unread_runs(rot)
    out = []
    for sign in (1.0, -1.0):
        v = np.where(np.isfinite(mid), sign * mid, -np.inf)
        k = int(np.argmax(v))
        if v[k] < min_deg or np.isfinite(rot[k]):
            continue
        lo, hi = next((lo, hi) for lo, hi in runs if lo <= k <= hi)
        if levels[hi] - levels[lo] >= min_span - 1e-6 and (levels[lo], levels[hi]) not in out:
            out.append((float(levels[lo]), float(levels[hi])))
    return out


# figures that read the back in the patient frame: with the back and front (and so left and right) in doubt,
# none of them can be told; the trunk's length and the whole-torso asymmetry do not depend on the facing
SIDED = ("lateral_deviation_mm", "surface_rotation_deg", "spine_lateral_deviation_mm", "midline_rotation_deg",
         "hump_mm", "hump_angle_deg", "hump", "hump_angle", "trunk_imbalance_mm", "trunk_inclination_mm", "regions", "apex",
         "cobb_estimate_deg", "cobb_estimate", "pelvic_obliquity_mm", "pelvic_obliquity_deg", "pelvic_torsion_deg")

# figures read at the lumbar dimples
PELVIC = ("pelvic_obliquity_mm", "pelvic_obliquity_deg", "pelvic_torsion_deg")

COBB_NOTE = ("estimates of the curves' Cobb angles from the back's surface, not radiographs; their error against "
             "the simulator's true spines is in docs/analysis.md")


# figures that rest on VP and SP (the sections between them, the line joining them, the length): a landmark
# placed by a fallback makes them not measurable; the whole-torso asymmetry does not rest on them
LANDMARKED = SIDED + ("trunk_length_mm", "kyphotic_angle_deg", "lordotic_angle_deg", "sagittal_levels")


def withhold(report: dict, reason: str, keys=SIDED, landmarks=(), in_regions: bool = False) -> dict:
    """Replace the figures ``keys`` of an indices report by None, in place, and say why (and which landmarks
    a clinician should mark). ``in_regions``: the same figures of every region too (a figure withheld over the
    whole trunk cannot be told in a part of it either)."""
    def blank(d, key):
        v = d[key]
        d[key] = {k: None for k in v} if isinstance(v, dict) and key not in NESTED else None

    for key in keys:
        if key in report:
            blank(report, key)
        for region in (report.get("regions") or {}).values() if in_regions else ():
            if key in region:
                blank(region, key)
    before = report.get("not_measurable")
    if before:  # a second reason (e.g. the dimples after the trunk's ends): both are told
        report["not_measurable"] = {
            "indices": list(dict.fromkeys([*before["indices"], *keys])),
            "reason": f"{before['reason']}; {reason}", "mark": list(dict.fromkeys([*before["mark"], *landmarks]))}
    else:
        report["not_measurable"] = {"indices": list(keys), "reason": reason, "mark": list(landmarks)}
    return report


# withheld whole, not key by key (their keys are levels and names, not figures)
NESTED = ("regions", "apex", "cobb_estimate", "sagittal_levels")


def _clinician_facing(torso: Torso, landmarks: dict | None) -> dict | None:
    """A facing prior from the clinician's vertebra prominens: the back is where the clinician marked it."""
    vp = (landmarks or {}).get("vertebra_prominens")
    if vp is None:
        return None
    vp = np.asarray(vp, float).reshape(3)
    # the trunk's axis through the shoulders, the 150 mm below the mark: at the mark's own height a scan cut at
    # C7 has only a few shoulder-top points, whose middle can lie beside the neck. A mark with hardly any
    # surface below it (far above the scan) says nothing of the facing
    z = torso.points[:, 2]
    band = (z >= vp[2] - 150.0) & (z <= vp[2])
    if band.sum() < 200:
        return None
    axis = np.median(torso.points[band, :2], axis=0)
    v = np.array([vp[0] - axis[0], vp[1] - axis[1], 0.0])
    if np.linalg.norm(v) < 20.0:  # on the axis: says nothing of the facing
        return None
    return {"posterior": (v / np.linalg.norm(v)).tolist(), "back_towards": [], "source": "clinician"}


def compute_indices(torso: Torso, cfg: AnalysisConfig | None = None, landmarks: dict | None = None) -> dict:
    """The ``torso-indices/1`` report of one torso (see :func:`analyse_torso`)."""
    return analyse_torso(torso, cfg, landmarks).report
