"""Pictures for the clinician, rendered off screen (pyvista/VTK for surfaces, matplotlib for trends).

Every function writes PNG files and returns their paths; none needs a display
(``pyvista.OFF_SCREEN``; VTK falls back to an off-screen context when there is
no X server). Views are set in the patient frame: *back* looks at the back
from behind, *side* at the patient's right side, *top* down from above.

Public functions (called by the clinic service from a Celery task):

- ``torso_views(torso, out_dir, frame=None, size=(800, 1000)) -> list[str]``
- ``deformation_picture(points, deformation_mm, out_png, frame=None, limit_mm=None, mdc_mm=None) -> str``
- ``asymmetry_picture(torso, asymmetry_mm, out_png, frame=None, limit_mm=None) -> str``
- ``trend_picture(visits, out_png, mdc=None, figures=None) -> str``
- ``torso_pictures(torso_ply, out_dir) -> dict`` and ``comparison_pictures(comparison_dir, out_dir) -> dict``:
  everything for one visit / one comparison from the files the commands write.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .frame import PatientFrame, detect_posterior, frame_from_posterior
from .torso import Torso, read_torso

VIEWS = ("back", "side", "top", "front")
LABELS = {"back": "back", "side": "right side", "top": "top", "front": "front"}


def _pv():
    import pyvista as pv

    pv.OFF_SCREEN = True
    return pv


def default_frame(points: np.ndarray) -> PatientFrame:
    """A patient frame from the shape alone (posterior detected, origin at the centroid)."""
    post, _ = detect_posterior(points)
    return frame_from_posterior(post, np.median(points, axis=0))


def _view_axes(frame: PatientFrame, view: str):
    """Direction from the subject towards the camera, and the picture's up, for a named view."""
    left, post, up = frame.R
    direction = {"back": post, "front": -post, "side": -left, "top": up}[view]
    return direction, (post if view == "top" else up)


def _camera(plotter, frame: PatientFrame, points: np.ndarray, view: str, aspect: float):
    """Parallel projection from the named side, the points' extent filling the picture with a margin."""
    direction, up = _view_axes(frame, view)
    right = np.cross(up, direction)
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    rel = points - centre
    w = np.ptp(rel @ right) if len(points) else 1.0
    h = np.ptp(rel @ up) if len(points) else 1.0
    extent = float(np.max(np.ptp(points, axis=0))) if len(points) else 1.0
    plotter.camera.position = (centre + 3 * extent * direction).tolist()
    plotter.camera.focal_point = centre.tolist()
    plotter.camera.up = up.tolist()
    plotter.camera.parallel_projection = True
    plotter.reset_camera_clipping_range()
    plotter.camera.parallel_scale = 0.55 * max(h, w / aspect)


def _side_labels(plotter, frame: PatientFrame, view: str, font_size: int = 11):
    """The patient's left and right written on the picture's edges, from the frame, so anyone can check them."""
    direction, up = _view_axes(frame, view)
    screen_right = np.cross(up, direction)
    s = float(frame.R[0] @ screen_right)
    if abs(s) < 0.5:
        return
    left_pos, right_pos = ("lower_right", "lower_left") if s > 0 else ("lower_left", "lower_right")
    plotter.add_text("L (patient's left)", position=left_pos, font_size=font_size, color="black")
    plotter.add_text("R (patient's right)", position=right_pos, font_size=font_size, color="black")


def _facing(normals, frame, view):
    """Points whose normal faces the camera of ``view`` (a cloud has no occlusion of its own)."""
    if normals is None:
        return slice(None)
    direction, _ = _view_axes(frame, view)
    return np.asarray(normals) @ direction > -0.1


def _cloud(points, normals=None, scalars=None, name="values"):
    pv = _pv()
    cloud = pv.PolyData(np.asarray(points, float))
    if normals is not None:
        cloud.point_data["Normals"] = np.asarray(normals, float)
    if scalars is not None:
        cloud.point_data[name] = np.asarray(scalars, float)
    return cloud


def _render(points, normals, out_png, frame, view, size, point_size, title=None, **mesh_kw):
    pv = _pv()
    p = pv.Plotter(off_screen=True, window_size=list(size))
    p.set_background("white")
    keep = _facing(normals, frame, view)
    cloud = _cloud(np.asarray(points)[keep], None if normals is None else np.asarray(normals)[keep])
    p.add_mesh(cloud, point_size=point_size, render_points_as_spheres=True, lighting=True, **mesh_kw)
    _camera(p, frame, np.asarray(cloud.points), view, size[0] / size[1])
    _side_labels(p, frame, view)
    if title:
        p.add_text(title, position="upper_left", font_size=12, color="black")
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    p.screenshot(str(out_png))
    p.close()
    return str(out_png)


def _point_size(points, size):
    from .torso import point_spacing

    extent = float(np.max(points.max(axis=0) - points.min(axis=0)))
    px_per_mm = min(size) / (1.1 * extent)
    return float(np.clip(3.0 * point_spacing(points) * px_per_mm, 3.0, 14.0))


def torso_views(torso: Torso | str, out_dir, frame: PatientFrame | None = None, size=(800, 1000),
                views=VIEWS, titles: dict | None = None) -> list[str]:
    """Shaded pictures of a torso (a :class:`Torso` or a PLY path) from the back, side, top and front.

    Writes ``out_dir/torso-<view>.png``, the patient's left and right marked on each; returns the paths
    in ``views`` order. ``titles``: view -> title (default the view's name).
    """
    if not isinstance(torso, Torso):
        torso = read_torso(torso)
    frame = frame or default_frame(torso.points)
    ps = _point_size(torso.points, size)
    titles = {**LABELS, **(titles or {})}
    return [_render(torso.points, torso.normals, Path(out_dir) / f"torso-{v}.png", frame, v, size, ps, title=titles[v],
                    color="#e0b8a0", smooth_shading=True, specular=0.2) for v in views]


def _facing_titles(report: dict) -> dict:
    """View titles that say how the patient's facing was found (and when it is in doubt)."""
    facing = (report.get("frame") or {}).get("facing") or {}
    how = {"rig": "facing from the rig's footplate", "shape": "facing from the torso's shape",
           "clinician": "facing from the clinician's landmark", "given": "facing given"}.get(facing.get("method"), "")
    note = "FACING UNCERTAIN: sides not measured" if facing.get("status") == "uncertain" else how
    return {v: f"{LABELS[v]} ({note})" if note else LABELS[v] for v in VIEWS}


def _scalar_picture(points, values, out_png, frame, limit_mm, title, bar_title, size, views, cmap, mdc_mm=None,
                    normals=None):
    pv = _pv()
    points = np.asarray(points, float)
    values = np.asarray(values, float)
    finite = values[np.isfinite(values)]
    if limit_mm is None:
        limit_mm = float(np.percentile(np.abs(finite), 98)) if len(finite) else 1.0
        limit_mm = max(limit_mm, 0.5)
    frame = frame or default_frame(points)
    if normals is None:
        from .torso import make_torso

        normals = make_torso(points).normals
    sub = (size[0] // len(views), size[1])
    ps = _point_size(points, sub)
    p = pv.Plotter(off_screen=True, window_size=list(size), shape=(1, len(views)), border=False)
    for k, v in enumerate(views):
        p.subplot(0, k)
        p.set_background("white")
        keep = _facing(normals, frame, v)
        cloud = _cloud(points[keep], None, values[keep], bar_title)
        p.add_mesh(cloud, scalars=bar_title, cmap=cmap, clim=[-limit_mm, limit_mm], nan_color="lightgrey",
                   point_size=ps, render_points_as_spheres=True, show_scalar_bar=False)
        _camera(p, frame, points[keep], v, 0.85 * sub[0] / sub[1])
        p.add_text(LABELS[v], position="upper_left", font_size=10, color="black")
        if not (title and k == 0):  # the first view's lower edge holds the title
            _side_labels(p, frame, v, font_size=8)
    p.subplot(0, len(views) - 1)
    p.add_scalar_bar(title="mm", color="black", vertical=True, n_labels=5, fmt="%+.1f",
                     position_x=0.86, position_y=0.15, height=0.7, width=0.07)
    if title:
        p.subplot(0, 0)
        text = f"{title}, mm" if mdc_mm is None else f"{title}, mm  (minimal detectable change {mdc_mm:.2f} mm)"
        p.add_text(text, position="lower_left", font_size=9, color="black")
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    p.screenshot(str(out_png))
    p.close()
    return str(out_png)


def deformation_picture(points, deformation_mm, out_png, frame: PatientFrame | None = None,
                        limit_mm: float | None = None, mdc_mm: float | None = None, size=(1400, 900),
                        views=("back", "side", "front"), normals=None) -> str:
    """The deformation map: later points (earlier frame) coloured by signed normal distance (mm).

    Diverging scale (blue inward, red outward) symmetric about zero, limit
    ``limit_mm`` (default: the 98th percentile of |deformation|), legend in mm;
    points without a value in grey. ``mdc_mm`` is written under the title.
    """
    return _scalar_picture(points, deformation_mm, out_png, frame, limit_mm, "deformation since the earlier visit",
                           "deformation (mm)", size, views, "RdBu_r", mdc_mm, normals)


def asymmetry_picture(torso: Torso, asymmetry_mm, out_png, frame: PatientFrame | None = None,
                      limit_mm: float | None = None, size=(1400, 900), views=("back", "side", "front")) -> str:
    """The asymmetry map: each trunk point's signed distance to the torso's mirror image (mm, + stands out)."""
    return _scalar_picture(torso.points, asymmetry_mm, out_png, frame, limit_mm, "asymmetry (torso vs its mirror image)",
                           "asymmetry (mm)", size, views, "PuOr_r", None, torso.normals)


TREND_FIGURES = (("lateral_deviation_mm.max", "lateral deviation, max (mm)"),
                 ("lateral_deviation_mm.rms", "lateral deviation, RMS (mm)"),
                 ("surface_rotation_deg.max", "surface rotation, max (deg)"),
                 ("surface_rotation_deg.rms", "surface rotation, RMS (deg)"),
                 ("hump_mm", "hump (mm)"), ("trunk_imbalance_mm", "trunk imbalance (mm)"),
                 ("asymmetry_mm", "asymmetry (mm)"), ("trunk_length_mm", "trunk length VP-SP (mm)"))


def trend_picture(visits, out_png, mdc: dict | None = None, figures=TREND_FIGURES, size_in=(11, 8)) -> str:
    """Trend of every index over the visits, one panel per index, with the MDC band about the first visit.

    ``visits``: list of ``(label, indices)`` in time order; ``label`` a string or a
    ``datetime``/``date`` (then the x axis is time); ``indices`` a ``torso-indices/1``
    dict. ``mdc``: figure -> mm or ``{"mdc": mm}`` (keys as in ``figures``, e.g.
    ``"hump_mm"``, ``"surface_rotation_deg.max"``).
    """
    # a Figure of its own (Agg canvas), not pyplot: a library call must not switch the process's backend
    from matplotlib.figure import Figure

    from .repeatability import flatten

    labels = [v[0] for v in visits]
    flat = [flatten(v[1]) for v in visits]
    is_time = all(hasattr(lab, "year") for lab in labels) and labels
    xs = labels if is_time else list(range(len(labels)))
    n = len(figures)
    cols = 2
    rows = (n + 1) // 2
    fig = Figure(figsize=size_in)
    axes = fig.subplots(rows, cols, sharex=True, squeeze=False)
    for k, (key, title) in enumerate(figures):
        ax = axes[k // cols][k % cols]
        ys = [f.get(key, np.nan) for f in flat]
        ax.plot(xs, ys, "o-", color="#1f4e79")
        m = (mdc or {}).get(key)
        m = m.get("mdc") if isinstance(m, dict) else m
        if m is not None and np.isfinite(ys[0]):
            ax.axhspan(ys[0] - m, ys[0] + m, color="#9ecae1", alpha=0.4, label="MDC about the first visit")
            for x, y in zip(xs[1:], ys[1:]):
                if np.isfinite(y) and abs(y - ys[0]) > m:
                    ax.plot([x], [y], "^", color="#c0392b", markersize=11, zorder=3)  # a shape as well as a colour
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    if not is_time:
        for ax in axes[-1]:
            ax.set_xticks(xs)
            ax.set_xticklabels([str(lab) for lab in labels], rotation=20, fontsize=8)
    fig.suptitle("surface indices over the visits (red \u25b2: change beyond the MDC)", fontsize=11)
    fig.tight_layout()
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=100)
    return str(out_png)


def torso_pictures(torso_ply, out_dir, landmarks: dict | None = None) -> dict:
    """Everything for one visit from ``torso.ply``: shaded views and the asymmetry map.

    Returns ``{"views": [png, ...], "asymmetry": png, "indices": torso-indices/1 dict}``.
    """
    from .indices import analyse_torso

    torso = read_torso(torso_ply)
    a = analyse_torso(torso, landmarks=landmarks)
    out = Path(out_dir)
    views = torso_views(torso, out, a.frame, titles=_facing_titles(a.report))
    asym = asymmetry_picture(torso, a.asymmetry_mm, out / "asymmetry.png", a.frame)
    return {"views": views, "asymmetry": asym, "indices": a.report}


def comparison_pictures(comparison_dir, out_dir, mdc_mm: float | None = None) -> dict:
    """The deformation map of a ``torsoscan compare`` output folder (reads ``deformation.ply``)."""
    from recon_engine.surface import read_ply

    ply = read_ply(Path(comparison_dir) / "deformation.ply")
    d = ply["data"]["deformation_mm"]
    png = deformation_picture(ply["points"], d, Path(out_dir) / "deformation.png", mdc_mm=mdc_mm,
                              normals=ply.get("normals"))
    return {"deformation": png}
