"""The patient's frame: vertical from the rig, facing direction and mid-sagittal plane from the shape.

Patient frame (mm): x towards the patient's left, y posterior (out of the
back), z up (the rig's +Z, as the test field stands); right-handed. For the
simulator's subject standing at rest it coincides with the world frame.
Reported lateral values are turned to the clinical sign: positive towards the
patient's right, i.e. ``-x``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import RigidConfig
from .rigid import register_rigid
from .torso import PlaneIndex, Torso

_AXES = {"+x": (1, 0), "-x": (-1, 0), "+y": (0, 1), "-y": (0, -1)}


@dataclass
class PatientFrame:
    """``p_patient = R @ (p_rig - origin)``; rows of ``R``: left, posterior, up (unit, rig frame)."""

    R: np.ndarray
    origin: np.ndarray

    def to_patient(self, p):
        return (np.asarray(p, float) - self.origin) @ self.R.T

    def to_rig(self, q):
        return np.asarray(q, float) @ self.R + self.origin

    def rotate(self, n):
        return np.asarray(n, float) @ self.R.T

    def to_dict(self):
        return {"origin_mm": self.origin.tolist(), "left": self.R[0].tolist(), "posterior": self.R[1].tolist(),
                "up": self.R[2].tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "PatientFrame":
        """The frame :meth:`to_dict` wrote (a torso-indices/1 report's ``frame``)."""
        return cls(R=np.array([d["left"], d["posterior"], d["up"]], float), origin=np.asarray(d["origin_mm"], float))


def frame_from_posterior(posterior, origin) -> PatientFrame:
    """The frame whose y is the horizontal part of ``posterior`` and z the rig's +Z."""
    z = np.array([0.0, 0.0, 1.0])
    y = np.array([posterior[0], posterior[1], 0.0])
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return PatientFrame(np.vstack([x, y, z]), np.asarray(origin, float))


def width_axis(points: np.ndarray, with_ratio: bool = False):
    """Horizontal unit vector of the trunk's largest horizontal spread (the left-right axis, sign arbitrary).

    ``with_ratio``: also the ratio of the largest to the smallest horizontal spread (variance; near 1 for
    a round trunk, whose width axis then says little).
    """
    z0, z1 = np.percentile(points[:, 2], [20, 80])
    p = points[(points[:, 2] >= z0) & (points[:, 2] <= z1), :2]
    p = p - np.median(p, axis=0)
    val, vec = np.linalg.eigh(p.T @ p)
    w = np.array([vec[0, 1], vec[1, 1], 0.0])
    return (w, float(val[1] / max(val[0], 1e-12))) if with_ratio else w


def facing_score(points: np.ndarray, direction: np.ndarray, half_width_mm: float = 30.0) -> float:
    """How convex (mm) the midline profile is on the side ``direction`` points to.

    Along the trunk's vertical midline, the outermost extent in ``direction`` at
    every height; the score is the mean extent of the middle 40 % of the heights
    minus the chord between the lowest and highest 15 %. The back is concave
    there (lumbar lordosis between sacrum and thoracic kyphosis: negative score),
    the front convex (abdomen and chest: positive).
    """
    d = np.asarray(direction, float)
    across = np.cross([0.0, 0.0, 1.0], d)
    c = np.median(points[:, :2], axis=0)
    rel = points[:, :2] - c
    a = rel @ across[:2]
    e = rel @ d[:2]
    mid = np.abs(a) < half_width_mm
    z = points[mid, 2]
    ext = e[mid]
    lo, hi = np.percentile(points[:, 2], [2, 98])
    edges = np.linspace(lo, hi, 41)
    prof = []
    for k in range(40):
        sel = (z >= edges[k]) & (z < edges[k + 1])
        prof.append(np.max(ext[sel]) if sel.sum() >= 3 else np.nan)
    prof = np.asarray(prof)
    if np.isnan(prof).sum() > 20:
        return 0.0
    ends = np.nanmean(prof[:6]), np.nanmean(prof[-6:])
    middle = np.nanmean(prof[12:28])
    return float(middle - 0.5 * (ends[0] + ends[1]))


def midline_sagitta(points: np.ndarray, direction: np.ndarray, half_width_mm: float = 60.0,
                    slice_mm: float = 10.0, bins: int = 10) -> tuple[float, int]:
    """How the skin curves across the midline on the side ``direction`` points to (mm) and in how many slices.

    In every horizontal slice (``slice_mm`` high) where the trunk spans well
    beyond ``half_width_mm`` either side of its vertical axis, the outermost
    extent in ``direction`` is read in ``bins`` bins across the midline and a
    parabola fitted; its sagitta over ``half_width_mm`` is negative where the
    skin bulges out (the belly, the chest) and near zero or positive where it
    is flat or grooved (the back: broad, with the spinal furrow between the
    erector muscles). The median over the slices does not depend on where the
    scan is cut at the top or the bottom, which the profile score does.
    Returns ``(sagitta_mm, slices)``; NaN with fewer than 5 slices.
    """
    from .torso import axis_points

    d = np.asarray(direction, float)[:2]
    d = d / np.linalg.norm(d)
    across = np.array([-d[1], d[0]])
    rel = points[:, :2] - axis_points(points, points[:, 2])
    a, e = rel @ across, rel @ d
    zb = np.floor((points[:, 2] - points[:, 2].min()) / slice_mm).astype(int)
    nz = int(zb.max()) + 1
    ab = np.floor((a + half_width_mm) / (2 * half_width_mm / bins)).astype(int)
    inside = (ab >= 0) & (ab < bins)
    ext = np.full((nz, bins), -np.inf)
    np.maximum.at(ext, (zb[inside], ab[inside]), e[inside])
    lo, hi = np.full(nz, np.inf), np.full(nz, -np.inf)
    np.minimum.at(lo, zb, a)
    np.maximum.at(hi, zb, a)
    # the trunk, not the neck or a single leg: it reaches well past the window on both sides
    ok = np.isfinite(ext).all(axis=1) & (lo < -1.6 * half_width_mm) & (hi > 1.6 * half_width_mm)
    if ok.sum() < 5:
        return float("nan"), int(ok.sum())
    ac = -half_width_mm + (np.arange(bins) + 0.5) * 2 * half_width_mm / bins
    A = np.column_stack([np.ones(bins), ac, ac ** 2])
    coef = np.linalg.lstsq(A, ext[ok].T, rcond=None)[0]
    return float(np.median(coef[2] * half_width_mm ** 2)), int(ok.sum())


def mirror_misfit(points: np.ndarray, normal: np.ndarray, sample: int = 4000, cap_mm: float = 20.0) -> float:
    """Mean distance (mm, each capped at ``cap_mm``) of the points reflected about the vertical plane through
    their median with horizontal ``normal`` to the nearest point: small for the mid-sagittal plane."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    idx = rng.choice(len(points), min(sample, len(points)), replace=False)
    n = np.array([normal[0], normal[1], 0.0]) / np.linalg.norm(normal[:2])
    c = np.median(points, axis=0)
    q = points[idx] - 2.0 * ((points[idx] - c) @ n)[:, None] * n
    d, _ = cKDTree(points).query(q, distance_upper_bound=cap_mm)
    return float(np.mean(np.minimum(d, cap_mm)))


# a back and a front differ by 3.3-11 mm of midline sagitta on 42 simulated scans (two bodies, three builds,
# six crops, five yaws): below 2 mm the cue decides nothing; below 4 mm it needs the profile's agreement
SAGITTA_DECISIVE_MM = 2.0
SAGITTA_SURE_MM = 4.0
PROFILE_DECISIVE_MM = 15.0  # the profile cue's margin that counts as an opinion (it flips with the crop)


def detect_posterior(points: np.ndarray, facing: str | None = None, prior: dict | None = None) -> tuple[np.ndarray, dict]:
    """Posterior unit vector (horizontal, rig frame) and the evidence for it.

    The patient's left and right follow from the posterior direction (x = posterior x up), so it must
    come from evidence that noise cannot flip:

    - ``facing`` ("+x", "-x", "+y", "-y"): given by the user; taken as it is.
    - ``prior``: the rig's footplate, ``{"posterior": [x, y, z], "back_towards": [...]}`` (the torso
      file's ``torsoscan posterior`` comment, see :func:`recon_engine.results.posterior_comment`);
      it decides the sign, and the shape only checks it.
    - the shape: the depth axis (perpendicular to the mid-sagittal plane's normal, the better mirror
      plane of the two horizontal principal axes), its sign from the midline sagitta (the back is flat
      or grooved across the midline, the front bulges) and, where that is weak, the profile score.

    ``info["status"]`` is "certain" or "uncertain" (then ``info["reason"]`` says why): an uncertain
    facing means the patient's sides cannot be told on this scan.
    """
    if facing is not None:
        if facing not in _AXES:
            raise ValueError(f"facing {facing!r}: choose one of {sorted(_AXES)}")
        v = np.array([*_AXES[facing], 0.0], float)
        return v, {"method": "given", "facing": facing, "status": "certain"}
    w, spread_ratio = width_axis(points, with_ratio=True)
    other = np.array([-w[1], w[0], 0.0])
    mis_w, mis_o = mirror_misfit(points, w), mirror_misfit(points, other)
    # a round trunk (a heavy body, arms held forward) has no clear width axis: then the left-right axis is the
    # normal of the clearly better mirror plane (the bodies' mid-sagittal planes fit 3-6x better than their
    # coronal ones); a clearly wide trunk keeps its width axis (a scoliotic shift spoils its mirror symmetry)
    if spread_ratio < 1.5 and mis_o < 0.6 * mis_w:
        w = other
    depth = np.cross([0.0, 0.0, 1.0], w)
    sag_plus, n_slices = midline_sagitta(points, depth)
    sag_minus, _ = midline_sagitta(points, -depth)
    prof_plus, prof_minus = facing_score(points, depth), facing_score(points, -depth)
    sag_margin = sag_plus - sag_minus  # > 0: +depth is the flatter side, the back
    prof_margin = prof_minus - prof_plus  # > 0: +depth is the concave profile, the back
    cues = {"midline_sagitta_mm": {"plus": sag_plus, "minus": sag_minus, "slices": n_slices},
            "profile_mm": {"plus": prof_plus, "minus": prof_minus},
            "mirror_misfit_mm": {"width_axis": mis_w, "other_axis": mis_o}, "spread_ratio": spread_ratio}
    sag_vote = float(np.sign(sag_margin)) if np.isfinite(sag_margin) and abs(sag_margin) >= SAGITTA_DECISIVE_MM \
        else 0.0
    prof_vote = float(np.sign(prof_margin)) if abs(prof_margin) >= PROFILE_DECISIVE_MM else 0.0
    if sag_vote and (abs(sag_margin) >= SAGITTA_SURE_MM or prof_vote != -sag_vote):
        shape_sign, shape_status, why = sag_vote, "certain", ""
    elif sag_vote:
        shape_sign, shape_status = sag_vote, "uncertain"
        why = (f"the skin across the midline ({abs(sag_margin):.1f} mm flatter on one side) and the back's "
               "profile disagree on which side is the back")
    elif prof_vote:
        shape_sign, shape_status = prof_vote, "uncertain"
        why = "the skin across the midline does not tell the back from the front; only the profile does"
    else:
        shape_sign, shape_status = 1.0, "uncertain"
        why = "the torso's shape does not tell the back from the front"
    if prior is not None and prior.get("posterior") is not None:
        p = np.array([prior["posterior"][0], prior["posterior"][1], 0.0], float)
        p /= np.linalg.norm(p)
        sign = 1.0 if p @ depth >= 0 else -1.0
        along = abs(p @ depth) >= np.cos(np.radians(45.0))
        if prior.get("source") == "clinician":
            # the clinician marked the vertebra prominens on the back: that settles which end of the shape's depth
            # axis is the back. A mark beside that axis tells neither end and must not turn the frame (a VP
            # marked just above a scan cut at C7 once turned it by 88 deg): the shape decides then
            if along:
                return sign * depth, {"method": "clinician", "status": "certain", "cues": cues,
                                      "shape_agrees": bool(shape_sign == sign) if shape_status == "certain" else None}
            prior = None
    if prior is not None and prior.get("posterior") is not None:
        post = sign * depth if along else p
        arms = ", ".join(prior.get("back_towards") or []) or "the rig's back"
        info = {"method": "rig", "back_towards": prior.get("back_towards") or [], "status": "certain",
                "shape_agrees": bool(shape_sign == sign) if shape_status == "certain" else None, "cues": cues}
        # only both shape cues together overrule the footplate: on a sparse or holed scan one cue alone can
        # turn with a degree of sway (the demo's reduced rig: the front's sagitta went from -12 to -2 mm)
        if sag_vote and prof_vote == sag_vote and sag_vote != sign:
            info["status"] = "uncertain"
            info["reason"] = (f"the rig's footplate puts the patient's back towards arms {arms}, but the torso's "
                              "shape says the back faces the other way: was the patient standing the other way "
                              "round? Check the picture and repeat the scan")
        return post, info
    info = {"method": "shape", "status": shape_status, "cues": cues}
    if why:
        info["reason"] = why
    return shape_sign * depth, info


def mirror(torso: Torso, frame: PatientFrame) -> Torso:
    """The torso reflected about the frame's mid-sagittal plane (x = 0)."""
    H = frame.R.T @ np.diag([-1.0, 1.0, 1.0]) @ frame.R
    p = (torso.points - frame.origin) @ H.T + frame.origin
    return Torso(p, torso.normals @ H.T, {}, torso.source)


def symmetry_plane(torso: Torso, frame: PatientFrame, cfg: RigidConfig | None = None, mask=None,
                   index: PlaneIndex | None = None) -> dict:
    """Register the torso's mirror image to itself; the mid-sagittal plane and the asymmetry map.

    Returns ``{"frame": PatientFrame (x along the plane's normal, origin on the plane),
    "R", "t" (mirror image -> torso), "distance_mm" (N,) signed normal distance of each
    mirrored point to the torso (NaN off the surface), "over" (N,) bool}``.
    """
    cfg = cfg or RigidConfig(initial_distance_mm=60.0, min_distance_mm=3.0)
    m = mirror(torso, frame)
    index = index or PlaneIndex(torso)
    res = register_rigid(m, torso, cfg, initial=(np.eye(3), np.zeros(3)), fixed_index=index, weights_mask=mask)
    H = frame.R.T @ np.diag([-1.0, 1.0, 1.0]) @ frame.R
    A = res["R"] @ H
    vals, vecs = np.linalg.eigh(0.5 * (A + A.T))
    n = vecs[:, 0]
    n[2] = 0.0
    n /= np.linalg.norm(n)
    if n @ frame.R[0] < 0:
        n = -n
    # a point on the plane: midway between a point and its image
    x = torso.points if mask is None else torso.points[mask]
    img = ((x - frame.origin) @ H.T + frame.origin) @ res["R"].T + res["t"]
    origin = 0.5 * (x + img).mean(axis=0)
    post = np.cross([0.0, 0.0, 1.0], n)
    new = frame_from_posterior(post, origin)
    xm = m.points @ res["R"].T + res["t"]
    d, _, _, over = index.distances(xm, cfg.max_tangential)
    d = np.where(over, d, np.nan)
    return {"frame": new, "R": res["R"], "t": res["t"], "distance_mm": d, "over": over, "registration": res}
