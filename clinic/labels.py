"""The clinic's words for the analysis' figures: one place, used by every page.

Each index of a ``torso-indices/1`` report (flattened key, e.g.
``surface_rotation_deg.max``) has a clinical label, a unit, a one-line
meaning and, for the indices that have a side, the words for each sign
(the report's convention: lateral values positive towards the patient's
right, rotation positive when the right side of the back comes backwards).
No internal key is meant to reach a page: templates get :func:`label` and
friends, never the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from analysis.repeatability import SIDED_SCALARS


@dataclass(frozen=True)
class Index:
    label: str
    unit: str
    meaning: str
    positive: str | None = None  # what a positive value means, in the patient's words
    negative: str | None = None
    growth: bool = False  # a size that grows with the child: never a deformity


_DEV_POS, _DEV_NEG = "towards the patient's right", "towards the patient's left"
_ROT_POS, _ROT_NEG = "right side of the back turned backwards", "left side of the back turned backwards"
_HUMP_POS, _HUMP_NEG = "higher on the patient's right", "higher on the patient's left"

INDICES: dict[str, Index] = {
    "lateral_deviation_mm.max": Index(
        "Sideways deviation of the back's midline, largest", "mm",
        "How far the back's line of symmetry strays sideways from the line C7 – sacral point, at its largest.",
        _DEV_POS, _DEV_NEG),
    "lateral_deviation_mm.rms": Index(
        "Sideways deviation of the back's midline, over the trunk", "mm",
        "The same deviation averaged over the whole trunk (root mean square).", _DEV_POS, _DEV_NEG),
    "spine_lateral_deviation_mm.max": Index(
        "Estimated spine deviation, largest", "mm",
        "The spine's sideways deviation estimated from the back (midline moved by a model depth of the spine).",
        _DEV_POS, _DEV_NEG),
    "spine_lateral_deviation_mm.rms": Index(
        "Estimated spine deviation, over the trunk", "mm",
        "The estimated spine deviation averaged over the trunk (root mean square).", _DEV_POS, _DEV_NEG),
    "cobb_estimate_deg.max": Index(
        "Cobb angle, estimated from the surface (largest curve)", "°",
        "An estimate, not a radiograph: the angle between the end tangents of each curve of the spine line "
        "estimated beneath the back's midline. On simulated bodies it was 1.5° from the spine's true Cobb "
        "angle on average (at worst 7.5°); against radiographs surface estimates are less accurate, so a decision "
        "that needs the Cobb angle needs a radiograph.",
        "curve convex to the patient's right", "curve convex to the patient's left"),
    "surface_rotation_deg.max": Index(
        "Trunk rotation, largest", "°",
        "Rotation of a horizontal slice of the back, at its largest (what a scoliometer reads on the rib hump).",
        _ROT_POS, _ROT_NEG),
    "surface_rotation_deg.rms": Index(
        "Trunk rotation, over the trunk", "°",
        "The slices' rotation averaged over the trunk (root mean square).", _ROT_POS, _ROT_NEG),
    "midline_rotation_deg.max": Index(
        "Skin rotation at the midline, largest", "°",
        "Tilt of the skin across the back's midline (rasterstereography's surface rotation), at its largest.",
        _ROT_POS, _ROT_NEG),
    "midline_rotation_deg.rms": Index(
        "Skin rotation at the midline, over the trunk", "°",
        "The skin's tilt at the midline averaged over the trunk (root mean square).", _ROT_POS, _ROT_NEG),
    "hump_mm": Index(
        "Rib / lumbar hump height", "mm",
        "How far the higher side's prominence of the back stands out beyond the other side's (the gap under a level "
        "laid across the back), at its largest.",
        _HUMP_POS, _HUMP_NEG),
    "hump_angle_deg": Index(
        "Hump angle", "°",
        "The hump as the angle of a line resting on both prominences, like a scoliometer laid on them.",
        _HUMP_POS, _HUMP_NEG),
    "trunk_imbalance_mm": Index(
        "Trunk imbalance (side to side)", "mm",
        "How far C7 (vertebra prominens) stands sideways of the sacral point: the trunk's balance seen from behind.",
        "C7 to the patient's right of the sacral point", "C7 to the patient's left of the sacral point"),
    "trunk_inclination_mm": Index(
        "Trunk inclination (front to back)", "mm",
        "How far C7 stands behind or in front of the sacral point: the trunk's balance seen from the side.",
        "C7 behind the sacral point", "C7 in front of the sacral point"),
    "asymmetry_mm": Index(
        "Back asymmetry (mirror)", "mm",
        "Average distance between the trunk and its own mirror image: 0 for a perfectly symmetric trunk."),
    "trunk_length_mm": Index(
        "Trunk length C7 – sacral point", "mm",
        "Distance from the vertebra prominens (C7) to the sacral point: grows with the child.", growth=True),
    "kyphotic_angle_deg": Index(
        "Kyphotic angle (surface)", "°",
        "Angle between the back's tangents at the top of the thoracic curve and at the thoracolumbar turn, "
        "seen from the side (rasterstereography's kyphotic angle, not a radiograph)."),
    "lordotic_angle_deg": Index(
        "Lordotic angle (surface)", "°",
        "Angle between the back's tangents at the thoracolumbar turn and above the sacrum, seen from the side "
        "(rasterstereography's lordotic angle, not a radiograph)."),
    "pelvic_obliquity_mm": Index(
        "Pelvic obliquity", "mm",
        "Height difference between the two lumbar dimples (over the pelvis's posterior iliac spines).",
        "pelvis higher on the patient's right", "pelvis higher on the patient's left"),
    "pelvic_torsion_deg": Index(
        "Pelvic torsion", "°",
        "How differently the back's surface at the two lumbar dimples faces up or down: a twist of the pelvis.",
        "right side of the pelvis facing more upwards", "left side of the pelvis facing more upwards"),
}

# the order of the tables (the full set) and of a headline (the largest values, one per index)
TABLE_KEYS = ("lateral_deviation_mm.max", "lateral_deviation_mm.rms", "spine_lateral_deviation_mm.max",
              "cobb_estimate_deg.max", "surface_rotation_deg.max", "surface_rotation_deg.rms", "midline_rotation_deg.max", "hump_mm",
              "hump_angle_deg", "trunk_imbalance_mm", "trunk_inclination_mm", "asymmetry_mm",
              "kyphotic_angle_deg", "lordotic_angle_deg", "pelvic_obliquity_mm", "pelvic_torsion_deg",
              "trunk_length_mm")
HEADLINE_KEYS = ("lateral_deviation_mm.max", "spine_lateral_deviation_mm.max", "surface_rotation_deg.max",
                 "midline_rotation_deg.max", "hump_mm", "hump_angle_deg", "trunk_imbalance_mm",
                 "trunk_inclination_mm", "asymmetry_mm")
GROWTH_KEYS = tuple(k for k, v in INDICES.items() if v.growth)

LANDMARK_NAMES = {"vertebra_prominens": "vertebra prominens (C7)", "sacral_point": "sacral point",
                  "dimple_left": "left lumbar dimple", "dimple_right": "right lumbar dimple"}

# comparison regions (torso-comparison/1) and the growth figures of a comparison
REGION_NAMES = {"back_upper": "Back, upper third", "back_middle": "Back, middle third",
                "back_lower": "Back, lower third", "back_left": "Back, patient's left half",
                "back_right": "Back, patient's right half", "chest": "Chest", "abdomen": "Abdomen",
                "trunk": "Whole trunk"}
GROWTH_FIGURES = (("trunk_length_mm", "Trunk length C7 – sacral point"), ("height_mm", "Trunk height"),
                  ("width_median_mm", "Trunk width (median)"))

# pictures of a torso or a comparison: title and what a screen reader should say
PICTURES = {
    "torso-back": ("Back view", "Shaded 3D surface of the torso seen from behind, with the vertebra prominens (VP), "
                                "the sacral point (SP) and the line of symmetry drawn; patient's left and right "
                                "marked L and R"),
    "torso-front": ("Front view", "Shaded 3D surface of the torso seen from the front, L and R marked"),
    "torso-side": ("Side view", "Shaded 3D surface of the torso seen from the patient's right side"),
    "torso-top": ("Top view", "Shaded 3D surface of the torso seen from above"),
    "asymmetry": ("Asymmetry map", "Colour map of the back against its mirror image on a fixed scale of ±15 mm: "
                                   "where one side stands out from the other"),
    "deformation": ("Deformation map", "Colour map of the change of the surface between the two scans on a fixed "
                                       "scale of ±10 mm (outward +, inward −); light grey: within the scanner's "
                                       "noise; dark grey: arms, neck and head, not compared"),
}


def index(key: str) -> Index:
    """The index of a flattened key (an unknown key gets a generic label, never the key itself)."""
    return INDICES.get(key) or Index("Other figure", "", "")


def label(key: str) -> str:
    return index(key).label


def unit(key: str) -> str:
    return index(key).unit


def picture(name: str) -> tuple[str, str]:
    """(title, alt text) of a stored picture."""
    return PICTURES.get(name, ("Picture", "Picture of the torso"))


def region(name: str) -> str:
    return REGION_NAMES.get(name, name.replace("_", " ").capitalize())


def landmark(name: str) -> str:
    return LANDMARK_NAMES.get(name, name.replace("_", " "))


def _fmt(value: float, u: str, digits: int = 1) -> str:
    return f"{value:.{digits}f}{'' if u == '°' else ' '}{u}"


def size_words(key: str, value) -> str:
    """A value with its side in words: "12.3 mm towards the patient's right" (no sign left to decode)."""
    if value is None or not math.isfinite(value):
        return "–"
    ix = index(key)
    if ix.positive and value != 0 and not key.endswith(".rms"):
        return f"{_fmt(abs(value), ix.unit)} {ix.positive if value > 0 else ix.negative}"
    return _fmt(value, ix.unit)


def change_words(key: str, earlier, later) -> str:
    """A change in words: for an index with a side, how much larger or smaller it grew on its side, or that it
    changed side (a signed difference such as "-45.7 mm" says neither); otherwise the signed difference."""
    if earlier is None or later is None:
        return "–"
    ix = index(key)
    u = ix.unit
    if ix.positive and not key.endswith(".rms"):
        if earlier * later < 0:
            return "changed side"
        d = abs(later) - abs(earlier)
        if round(abs(d), 1) == 0:  # "0.0° larger" reads as a change
            return "unchanged"
        return f"{_fmt(abs(d), u)} {'larger' if d > 0 else 'smaller'}"
    d = later - earlier
    return f"{d:+.1f}{'' if u == '°' else ' '}{u}"


def change_texts(key: str, c: dict) -> dict:
    """A change of :func:`analysis.repeatability.index_changes` in words: ``{"earlier", "later", "from_to",
    "change"}``. A figure compared side by side (an S curve has a curve on each side) names both sides, the
    one larger now first, so "largest" reads the same number here as on the visit page."""
    parts = c.get("sides") or []
    named = len(parts) > 1
    if not named:
        parts = [c]
    was = [size_words(key, p["earlier"]) for p in parts]
    now = [size_words(key, p["later"]) for p in parts]
    change = [change_words(key, p["earlier"], p["later"]) for p in parts]
    if named:
        change = [f"patient's {p['side']}: {words}" for p, words in zip(parts, change)]
    return {"earlier": "; ".join(was), "later": "; ".join(now),
            "from_to": "; ".join(f"{e} → {l}" for e, l in zip(was, now)), "change": "; ".join(change)}


def _trunk_height(sections) -> float | None:
    """Height of C7 above the sacral point from two sections (z = z_SP + level * height)."""
    if not sections or len(sections) < 2:
        return None
    a, b = sections[0], sections[-1]
    dl = b["level"] - a["level"]
    return (b["z_mm"] - a["z_mm"]) / dl if dl > 1e-9 else None


def _sides_from_sections(sections, field):
    """Each side's largest value with its level, for an index reported as one signed number (the hump)."""
    height = _trunk_height(sections)
    out = {}
    for side, sign in (("right", 1.0), ("left", -1.0)):
        best = None
        for s in sections or []:
            v = s.get(field)
            if v is None or not math.isfinite(v) or sign * v <= 0:
                continue
            if best is None or sign * v > best["size"]:
                best = {"size": sign * v, "level": s["level"],
                        "height_mm": s["level"] * height if height else None}
        out[side] = best
    return out


def sides(indices: dict, key: str) -> list[dict]:
    """Where an index is largest on each side: ``[{"side", "size", "level_percent", "height_mm", "words"}]``."""
    if not indices:
        return []
    base = key.split(".")[0]
    entry = indices.get(base)
    if isinstance(entry, dict) and ("right" in entry or "left" in entry):
        found = {s: entry.get(s) for s in ("right", "left")}
    elif base in SIDED_SCALARS:
        sided = indices.get(SIDED_SCALARS[base])
        if isinstance(sided, dict) and ("right" in sided or "left" in sided):
            found = {s: sided.get(s) for s in ("right", "left")}
        else:  # a report from before the hump's sides were stored
            found = _sides_from_sections(indices.get("sections"), base)
    else:
        return []
    ix = index(key)
    out = []
    for side in ("right", "left"):
        f = found.get(side)
        if not f or f.get("size") is None:
            continue
        where = ix.positive if side == "right" else ix.negative
        level = f.get("level")
        height = f.get("height_mm")
        at = ""
        if level is not None:
            at = f" at {100 * level:.0f} % of the trunk's height"
            if height is not None:
                at += f" ({height:.0f} mm above the sacral point)"
        out.append({"side": side, "size": f["size"], "level_percent": None if level is None else 100 * level,
                    "height_mm": height, "words": f"{_fmt(f['size'], ix.unit)} {where}{at}"})
    return out
