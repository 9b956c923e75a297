"""Pictures for the clinician: shaded surfaces (torso views, asymmetry and deformation maps) and trends.

Every function writes PNG files and returns their paths; none needs a display
or a GPU: surfaces are rasterised in numpy (:mod:`analysis.render`) and laid
out with matplotlib's ``Figure`` (no pyplot: a library call must not switch the
process's backend). Views are set in the patient frame: *back* looks at the
back from behind, *side* at the patient's right side, *top* down from above.

The surface drawn is the reconstruction's triangle mesh (``torso-mesh.ply``)
when it is given, else a triangulation of the points facing each view; either
way a shaded surface, not scattered points.

Maps: one fixed colour scale for every visit (:data:`DEFORMATION_LIMIT_MM`,
:data:`ASYMMETRY_LIMIT_MM`, written on the colour bar with its sign), a change
within the minimal detectable change in light grey, and what is not compared
(the arms, the neck and head above the vertebra prominens, skin off the earlier
surface) in dark grey, so an arm held differently does not look like a change.
The patient's left (L) and right (R) are written on every view they show in.

Public functions (called by the clinic service from a Celery task):

- ``torso_views(torso, out_dir, frame=None, size=(800, 1000), ..., mesh=None, landmarks=None, symmetry_line=None)``
- ``deformation_picture(points, deformation_mm, out_png, frame=None, limit_mm=None, mdc_mm=None, ...,
  mesh=None, trunk=None, landmarks=None) -> str`` (``deformation_figure``: the same, the Figure itself)
- ``asymmetry_picture(torso, asymmetry_mm, out_png, frame=None, limit_mm=None, ..., mesh=None) -> str``
- ``trend_picture(visits, out_png, mdc=None, figures=None) -> str``
- ``torso_pictures(torso_ply, out_dir, landmarks=None, mesh_ply=None) -> dict`` and
  ``comparison_pictures(comparison_dir, out_dir, mdc_mm=None, mesh_ply=None, indices=None) -> dict``:
  everything for one visit / one comparison from the files the commands write.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import render
from .frame import PatientFrame, detect_posterior, frame_from_posterior
from .torso import Torso, read_torso

VIEWS = ("back", "side", "top", "front")
LABELS = {"back": "back", "side": "right side", "top": "top", "front": "front"}

# one clinical colour scale for every visit, so two maps can be set side by side: beyond it the colour saturates
DEFORMATION_LIMIT_MM = 10.0
ASYMMETRY_LIMIT_MM = 15.0
SKIN = np.array([0.87, 0.72, 0.62])
MDC_GREY = np.array([0.86, 0.86, 0.86])  # a change within the minimal detectable change: noise
MASKED_GREY = np.array([0.55, 0.55, 0.55])  # not compared: arms, neck and head, skin off the other surface
LANDMARK_MARKS = {"vertebra_prominens": ("VP", "vertebra prominens"), "sacral_point": ("SP", "sacral point"),
                  "dimple_left": ("DL", "left dimple"), "dimple_right": ("DR", "right dimple")}
DPI = 100


def default_frame(points: np.ndarray) -> PatientFrame:
    """A patient frame from the shape alone (posterior detected, origin at the centroid)."""
    post, _ = detect_posterior(points)
    return frame_from_posterior(post, np.median(points, axis=0))


def frame_from_report(indices: dict | None) -> PatientFrame | None:
    """The patient frame a ``torso-indices/1`` report was measured in (None when it has none)."""
    f = (indices or {}).get("frame") or {}
    try:
        R = np.array([f["left"], f["posterior"], f["up"]], float)
        return PatientFrame(R, np.array(f["origin_mm"], float))
    except (KeyError, TypeError, ValueError):
        return None


def landmarks_from_report(indices: dict | None) -> dict:
    """name -> rig-frame point of the landmarks a ``torso-indices/1`` report placed."""
    out = {}
    for k, v in ((indices or {}).get("landmarks") or {}).items():
        p = (v or {}).get("position_mm")
        if p is not None:
            out[k] = np.array(p, float)
    return out


def symmetry_line(analysis) -> np.ndarray:
    """The line of symmetry of a :class:`analysis.indices.TorsoAnalysis` (or its report): rig-frame points (n, 3),
    from the sacral point up to the vertebra prominens."""
    sections = analysis.sections if hasattr(analysis, "sections") else (analysis or {}).get("sections") or []
    frame = analysis.frame if hasattr(analysis, "frame") else frame_from_report(analysis)
    q = np.array([[s.get("symmetry_point_mm", np.nan), s.get("depth_mm", np.nan), s.get("z_mm", np.nan)]
                  for s in sections], float).reshape(-1, 3)
    q = q[np.isfinite(q).all(axis=1)]
    return frame.to_rig(q) if frame is not None and len(q) else np.zeros((0, 3))


def read_mesh(mesh):
    """``(vertices, faces)`` from a mesh PLY path, a ``read_ply`` dict or a pair; None for none or no faces."""
    if mesh is None:
        return None
    if isinstance(mesh, (str, Path)):
        from recon_engine.surface import read_ply

        try:
            mesh = read_ply(mesh)
        except (OSError, ValueError, KeyError, IndexError, UnicodeDecodeError):
            return None
    if isinstance(mesh, dict):
        mesh = (mesh.get("points"), mesh.get("faces"))
    V, F = mesh
    if V is None or F is None or len(F) == 0:
        return None
    V = np.asarray(V, float)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    good = np.isfinite(V).all(axis=1)
    F = F[good[F].all(axis=1)]
    return (V, F) if len(F) else None


def trunk_region(points, frame: PatientFrame, vertebra_prominens=None) -> np.ndarray:
    """Which points (rig frame) belong to the trunk: True but for the arms (cut at the gaps beside the trunk,
    as the indices' sections are) and the neck and head (above the vertebra prominens, when it is known)."""
    from dataclasses import replace

    from .config import IndicesConfig
    from .indices import trunk_mask

    points = np.asarray(points, float)
    if len(points) == 0:
        return np.zeros(0, bool)
    P = frame.to_patient(points)
    ic = IndicesConfig()
    spacing = render.point_spacing(points)
    ic = replace(ic, grid_mm=max(ic.grid_mm, spacing), gap_mm=max(ic.gap_mm, 4.0 * spacing))
    top = float(P[:, 2].max())
    if vertebra_prominens is not None and np.all(np.isfinite(vertebra_prominens)):
        top = float(frame.to_patient(np.asarray(vertebra_prominens, float))[2])
    return trunk_mask(P, float(P[:, 2].min()) - 1.0, top, ic)


class _Scene:
    """What is drawn: a mesh, or a cloud triangulated per view; per-point values carried onto it."""

    def __init__(self, points, normals=None, mesh=None, values=None):
        self.points = np.asarray(points, float)
        self.normals = None if normals is None else np.asarray(normals, float)
        if self.normals is None and mesh is None:
            from .torso import make_torso

            self.normals = make_torso(self.points).normals
        self.values = None if values is None else np.asarray(values, float).reshape(len(self.points), -1)
        self.mesh = read_mesh(mesh)
        self.spacing = render.point_spacing(self.points) if len(self.points) > 20 else 5.0
        self._mesh_surface = None
        self._mesh_values = None
        if self.mesh is not None:
            s = render.mesh_surface(*self.mesh)
            from scipy.spatial import cKDTree

            tree = cKDTree(self.points)
            self._cull = self.normals is not None and len(s.faces) > 0  # only a mesh known to be wound outwards
            if self._cull:
                # the mesh wound outwards (as the cloud's normals point), so back faces can be culled
                fn = render.face_normals(s)
                _, j = tree.query(s.points[s.faces].mean(axis=1), k=1)
                if np.median(np.einsum("ij,ij->i", fn, self.normals[j])) < 0:
                    s = render.Surface(s.points, s.faces[:, ::-1].copy(), -s.normals)
            self._mesh_surface = s
            self._face_normals = render.face_normals(s)
            if self.values is not None:
                # each mesh vertex takes the nearest point's values; a vertex far from every point has none
                d, j = tree.query(s.points, k=1)
                vals = self.values[j].copy()
                vals[d > max(3.0 * self.spacing, 10.0)] = np.nan
                self._mesh_values = vals

    def surface(self, basis):
        """The surface for a view and its vertices' values: the mesh's faces turned to the viewer over the
        cloud's own triangulation set a little behind (it shows through the mesh's holes), or the cloud's."""
        cloud = None
        if self.normals is not None:
            # under a mesh the cloud only fills its holes: no squares at its points (they roughen the outline)
            cloud = render.facing_surface(self.points, self.normals, basis, 3.0 * self.spacing,
                                          fill=self._mesh_surface is None)
            cloud_values = None if self.values is None else self.values[cloud.index]
        if self._mesh_surface is None:
            return cloud, cloud_values
        mesh = (render.front_faces(self._mesh_surface, basis[2], self._face_normals) if self._cull
                else self._mesh_surface)
        if cloud is None:
            return mesh, self._mesh_values
        behind = render.Surface(cloud.points - 0.6 * self.spacing * basis[2], cloud.faces, cloud.normals)
        values = None if self.values is None else np.vstack([self._mesh_values, cloud_values])
        return render.combine(mesh, behind), values

    def extent_points(self):
        return self._mesh_surface.points if self._mesh_surface is not None else self.points


def _render_views(scene: _Scene, frame: PatientFrame, views, width: int, height: int, common_scale=False,
                  fit=None):
    """Each view rendered to ``width`` x ``height`` pixels: ``[(view, Rendered)]``; ``fit``: the rig-frame points
    the pictures are fitted to (default the whole surface)."""
    bases = [render.view_basis(frame, v) for v in views]
    surfaces = [scene.surface(b) for b in bases]
    fit = fit if fit is not None and len(fit) > 10 else None
    placements = [render.place(s.points if len(s.points) else scene.extent_points(), b, width, height,
                               within=fit) for (s, _), b in zip(surfaces, bases)]
    if common_scale and placements:
        scale = min(p.scale for p in placements)
        for p in placements:
            p.scale = scale
    out = []
    for v, (s, vals), p in zip(views, surfaces, placements):
        r = render.render(s, p, vals)
        out.append((v, r))
    return out


def _figure(width: int, height: int):
    from matplotlib.figure import Figure

    return Figure(figsize=(width / DPI, height / DPI), dpi=DPI)


def _image_axes(fig, rect, rendered: render.Rendered, img: np.ndarray):
    """Axes at ``rect`` (figure fraction) over a rendered picture, pixel coordinates as data coordinates.

    The picture is put on the figure pixel for pixel (``figimage``: no resampling); the axes, transparent and
    above it, carry what is drawn over it (markers, lines, words)."""
    H, W = rendered.tri.shape
    fw, fh = fig.get_size_inches() * fig.dpi
    if img.dtype != np.uint8:
        img = np.round(np.clip(img, 0.0, 1.0) * 255).astype(np.uint8)
    fig.figimage(img, xo=int(round(rect[0] * fw)), yo=int(round(rect[1] * fh)), origin="upper", zorder=0)
    ax = fig.add_axes(rect, zorder=1)
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.set_axis_off()
    ax.patch.set_visible(False)
    return ax


def side_of_left(frame: PatientFrame, view: str) -> str | None:
    """Where the patient's left is on a view's picture: ``"left"``, ``"right"`` or None (the side view)."""
    s = float(frame.R[0] @ render.view_basis(frame, view)[0])
    if abs(s) < 0.5:
        return None
    return "right" if s > 0 else "left"


def _side_marks(ax, frame: PatientFrame, view: str, fontsize=22):
    """A large L and R on the picture's edges, from the frame (the patient's own left and right)."""
    where = side_of_left(frame, view)
    if where is None:
        return
    for letter, words in (("L", "patient's\nleft"), ("R", "patient's\nright")):
        on_left = (letter == "L") == (where == "left")
        x, ha = (0.015, "left") if on_left else (0.985, "right")
        ax.text(x, 0.9, letter, transform=ax.transAxes, ha=ha, va="bottom", fontsize=fontsize, fontweight="bold",
                color="#1f1f1f", gid=f"side-{letter}")
        ax.text(x, 0.9, words, transform=ax.transAxes, ha=ha, va="top", fontsize=max(8, fontsize // 2.5),
                color="#1f1f1f")


def _skin_image(rendered: render.Rendered) -> np.ndarray:
    return render.compose(rendered, np.broadcast_to(SKIN, rendered.tri.shape + (3,)))


def _draw_landmarks(ax, rendered: render.Rendered, landmarks: dict | None, line=None):
    """Labelled markers at the landmarks the view sees; the line of symmetry (back view)."""
    handles = []
    if line is not None and len(line) > 1:
        xy, _ = rendered.placement.project(line)
        (h,) = ax.plot(xy[:, 0], xy[:, 1], "-", color="#1565c0", lw=2.0, label="line of symmetry", gid="symmetry-line")
        handles.append(h)
    for name, (short, long) in LANDMARK_MARKS.items():
        p = (landmarks or {}).get(name)
        if p is None or not np.all(np.isfinite(p)):
            continue
        p = np.asarray(p, float).reshape(1, 3)
        if not rendered.visible(p)[0]:
            continue
        xy, _ = rendered.placement.project(p)
        (h,) = ax.plot([xy[0, 0]], [xy[0, 1]], "o", ms=9, mfc="#ffd54f", mec="black", mew=1.5,
                       label=f"{short} {long}", gid=f"landmark-{name}")
        ax.annotate(short, (xy[0, 0], xy[0, 1]), xytext=(8, 4), textcoords="offset points", fontsize=11,
                    fontweight="bold", color="black",
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75})
        handles.append(h)
    if handles:
        ax.legend(handles=handles, loc="lower center", fontsize=8, ncol=min(3, len(handles)), frameon=True,
                  framealpha=0.85)


def _save(fig, out_png) -> str:
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=DPI, pil_kwargs={"compress_level": 3})  # a fifth larger, a third faster than 6
    return str(out_png)


def torso_views(torso: Torso | str, out_dir, frame: PatientFrame | None = None, size=(800, 1000),
                views=VIEWS, titles: dict | None = None, mesh=None, landmarks: dict | None = None,
                symmetry_line=None) -> list[str]:
    """Shaded pictures of a torso (a :class:`Torso` or a PLY path) from the back, side, top and front.

    Writes ``out_dir/torso-<view>.png``, the patient's left and right marked on each; returns the paths
    in ``views`` order. ``titles``: view -> title (default the view's name). ``mesh``: the reconstruction's
    triangle mesh (path or ``(vertices, faces)``), else the points are triangulated. ``landmarks``: name ->
    rig-frame point, drawn as labelled markers where seen; ``symmetry_line``: rig-frame points (n, 3), drawn
    on the back view.
    """
    if not isinstance(torso, Torso):
        torso = read_torso(torso)
    frame = frame or default_frame(torso.points)
    titles = {**LABELS, **(titles or {})}
    scene = _Scene(torso.points, torso.normals, mesh)
    W, H = size
    out = []
    for v, r in _render_views(scene, frame, views, W, H):
        fig = _figure(W, H)
        ax = _image_axes(fig, [0, 0, 1, 1], r, _skin_image(r))
        ax.text(0.01, 0.99, titles[v], transform=ax.transAxes, ha="left", va="top", fontsize=12)
        _side_marks(ax, frame, v)
        _draw_landmarks(ax, r, landmarks, symmetry_line if v == "back" else None)
        out.append(_save(fig, Path(out_dir) / f"torso-{v}.png"))
    return out


def render_view(torso: Torso | str, frame: PatientFrame, view: str, size=(800, 1000), mesh=None) -> render.Rendered:
    """The ``view`` picture as :func:`torso_views` renders it (its projection, z-buffer and shading), undrawn."""
    if not isinstance(torso, Torso):
        torso = read_torso(torso)
    if view not in VIEWS:
        raise ValueError(f"view {view!r}: one of {', '.join(VIEWS)}")
    (_, r), = _render_views(_Scene(torso.points, torso.normals, mesh), frame, [view], *size)
    return r


def pick_point(torso: Torso | str, frame: PatientFrame, view: str, x_px: float, y_px: float, size=(800, 1000),
               mesh=None, radius_px: float = 12.0):
    """The skin point under pixel ``(x_px, y_px)`` of the ``view`` picture that :func:`torso_views` draws with the
    same torso, frame, size and mesh (what a clinician clicked on): rig frame, mm; None when no skin was drawn
    within ``radius_px`` of it. The view is rendered again (the same projection, deterministic), and the point
    is the surface's own at that pixel (its depth from the z-buffer), not the nearest measured point."""
    r = render_view(torso, frame, view, size, mesh)
    rows, cols = np.nonzero(r.covered)
    if not len(rows):
        return None
    # the drawn pixel nearest the click (the click itself when it is on the skin)
    d2 = (cols + 0.5 - x_px) ** 2 + (rows + 0.5 - y_px) ** 2
    k = int(np.argmin(d2))
    if d2[k] > radius_px ** 2:
        return None
    row, col = rows[k], cols[k]
    pl = r.placement
    screen = np.array([pl.centre_mm[0] + (col + 0.5 - 0.5 * pl.width) / pl.scale,
                       pl.centre_mm[1] - (row + 0.5 - 0.5 * pl.height) / pl.scale, r.depth[row, col]])
    return screen @ pl.basis  # basis rows: screen right, up, towards the viewer (orthonormal, rig frame)


def _facing_titles(report: dict) -> dict:
    """View titles that say how the patient's facing was found (and when it is in doubt)."""
    facing = (report.get("frame") or {}).get("facing") or {}
    how = {"rig": "facing from the rig's footplate", "shape": "facing from the torso's shape",
           "clinician": "facing from the clinician's landmark", "given": "facing given"}.get(facing.get("method"), "")
    note = "FACING UNCERTAIN: sides not measured" if facing.get("status") == "uncertain" else how
    return {v: f"{LABELS[v]} ({note})" if note else LABELS[v] for v in VIEWS}


def map_colours(values: np.ndarray, limit_mm: float, cmap, mdc_mm: float | None = None,
                masked: np.ndarray | None = None) -> np.ndarray:
    """Base colours (..., 3) of a map: the colour scale within +-``limit_mm`` (saturating beyond), light grey
    within +-``mdc_mm``, dark grey where there is no value or ``masked``."""
    from matplotlib import colormaps

    v = np.asarray(values, float)
    rgb = colormaps[cmap](np.clip(0.5 + 0.5 * np.nan_to_num(v) / limit_mm, 0.0, 1.0))[..., :3]
    if mdc_mm is not None and mdc_mm > 0:
        rgb[np.abs(v) < mdc_mm] = MDC_GREY
    off = ~np.isfinite(v) if masked is None else (~np.isfinite(v) | masked)
    rgb[off] = MASKED_GREY
    return rgb


def _scalar_figure(points, values, frame, limit_mm, title, bar_label, size, views, cmap, mdc_mm=None,
                   normals=None, mesh=None, trunk=None, note=None):
    """A map's figure: one panel per view (axes with gid ``view-<view>``, the L and R texts ``side-L``,
    ``side-R``), the colour bar and the legend."""
    points = np.asarray(points, float)
    values = np.asarray(values, float)
    frame = frame or default_frame(points)
    keep = np.ones(len(points), float) if trunk is None else np.asarray(trunk, bool).astype(float)
    scene = _Scene(points, normals, mesh, np.column_stack([values, keep]))
    W, H = size
    bar_w, top_h, bottom_h = 150, 60, 64
    pw, ph = (W - bar_w) // len(views), H - top_h - bottom_h
    fig = _figure(W, H)
    fit = points[np.isfinite(values) & (keep > 0.5)]
    for k, (v, r) in enumerate(_render_views(scene, frame, views, pw, ph, common_scale=True, fit=fit)):
        val = r.value if r.value is not None else np.full(r.tri.shape + (2,), np.nan)
        colours = map_colours(val[..., 0], limit_mm, cmap, mdc_mm, masked=~(val[..., 1] > 0.5))
        ax = _image_axes(fig, [k * pw / W, bottom_h / H, pw / W, ph / H], r, render.compose(r, colours))
        ax.set_gid(f"view-{v}")
        ax.text(0.02, 1.0, f"seen from the {LABELS[v]}" if v != "side" else "seen from the patient's right",
                transform=ax.transAxes, ha="left", va="bottom", fontsize=11)
        _side_marks(ax, frame, v, fontsize=18)
    _colour_bar(fig, [(W - bar_w + 18) / W, (bottom_h + 0.08 * ph) / H, 22 / W, 0.84 * ph / H], limit_mm, cmap,
                bar_label, mdc_mm)
    fig.text(0.01, 1 - 6 / H, title, ha="left", va="top", fontsize=13, fontweight="bold")
    lines = [f"colour scale fixed at \u00b1{limit_mm:g} mm for every visit (stronger values show the end colour)"]
    if mdc_mm is not None:
        lines.append(f"light grey: within the minimal detectable change (\u00b1{mdc_mm:.2f} mm), "
                     "no change beyond the noise")
    lines.append(note or "dark grey: not measured")
    fig.text(0.01, 6 / H, "\n".join(lines), ha="left", va="bottom", fontsize=9)
    return fig


def _colour_bar(fig, rect, limit_mm, cmap, label, mdc_mm=None):
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    cax = fig.add_axes(rect)
    sm = ScalarMappable(Normalize(-limit_mm, limit_mm), colormaps[cmap])
    bar = fig.colorbar(sm, cax=cax, extend="both", format="%+g")
    bar.set_label(label, fontsize=9)
    bar.ax.tick_params(labelsize=9)
    if mdc_mm is not None and mdc_mm > 0:
        cax.axhspan(-mdc_mm, mdc_mm, color=tuple(MDC_GREY), zorder=3)
    cax.set_gid("colour-bar")
    return bar


DEFORMATION_BAR = "change since the earlier visit (mm)\n+ outwards (skin further out), \u2212 inwards"
DEFORMATION_NOTE = ("dark grey: not compared: the arms, the neck and head (above the vertebra prominens) and skin "
                    "with no earlier surface under it")


def deformation_picture(points, deformation_mm, out_png, frame: PatientFrame | None = None,
                        limit_mm: float | None = None, mdc_mm: float | None = None, size=(1400, 900),
                        views=("back", "side", "front"), normals=None, mesh=None, trunk=None,
                        landmarks: dict | None = None) -> str:
    """The deformation map written to ``out_png`` (see :func:`deformation_figure`)."""
    return _save(deformation_figure(points, deformation_mm, frame, limit_mm, mdc_mm, size, views, normals, mesh,
                                    trunk, landmarks), out_png)


def deformation_figure(points, deformation_mm, frame: PatientFrame | None = None, limit_mm: float | None = None,
                       mdc_mm: float | None = None, size=(1400, 900), views=("back", "side", "front"), normals=None,
                       mesh=None, trunk=None, landmarks: dict | None = None):
    """The deformation map: the later surface (earlier frame) coloured by signed normal distance (mm).

    Diverging scale (blue inward, red outward) fixed at +-``limit_mm`` (default :data:`DEFORMATION_LIMIT_MM`,
    the same for every visit); within +-``mdc_mm`` light grey. ``trunk`` (N,) bool: the points compared; else
    derived from ``frame`` and ``landmarks["vertebra_prominens"]`` (:func:`trunk_region`). ``mesh``: the later
    reconstruction's triangle mesh in the same frame as ``points``.
    """
    points = np.asarray(points, float)
    frame = frame or default_frame(points)
    if trunk is None:
        trunk = trunk_region(points, frame, (landmarks or {}).get("vertebra_prominens"))
    return _scalar_figure(points, deformation_mm, frame, limit_mm or DEFORMATION_LIMIT_MM,
                          "deformation since the earlier visit", DEFORMATION_BAR, size, views, "RdBu_r", mdc_mm,
                          normals, mesh, trunk, DEFORMATION_NOTE)


def asymmetry_picture(torso: Torso, asymmetry_mm, out_png, frame: PatientFrame | None = None,
                      limit_mm: float | None = None, size=(1400, 900), views=("back", "side", "front"),
                      mesh=None) -> str:
    """The asymmetry map: each trunk point's signed distance to the torso's mirror image (mm, + stands out),
    on a scale fixed at +-``limit_mm`` (default :data:`ASYMMETRY_LIMIT_MM`)."""
    fig = _scalar_figure(torso.points, asymmetry_mm, frame, limit_mm or ASYMMETRY_LIMIT_MM,
                         "asymmetry (torso vs its mirror image)",
                         "asymmetry (mm)\n+ stands out beyond the mirror image, \u2212 lies within", size, views,
                         "PuOr_r", None, torso.normals, mesh, None,
                         "dark grey: not measured: the arms, the neck and head, below the sacral point")
    return _save(fig, out_png)


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


def torso_pictures(torso_ply, out_dir, landmarks: dict | None = None, mesh_ply=None) -> dict:
    """Everything for one visit from ``torso.ply`` (and ``torso-mesh.ply`` when given): shaded views with the
    landmarks and the line of symmetry, and the asymmetry map.

    Returns ``{"views": [png, ...], "asymmetry": png, "indices": torso-indices/1 dict}``.
    """
    from .indices import analyse_torso

    torso = read_torso(torso_ply)
    a = analyse_torso(torso, landmarks=landmarks)
    out = Path(out_dir)
    mesh = read_mesh(mesh_ply)
    views = torso_views(torso, out, a.frame, titles=_facing_titles(a.report), mesh=mesh, landmarks=a.landmarks,
                        symmetry_line=symmetry_line(a))
    asym = asymmetry_picture(torso, a.asymmetry_mm, out / "asymmetry.png", a.frame, mesh=mesh)
    return {"views": views, "asymmetry": asym, "indices": a.report}


def comparison_pictures(comparison_dir, out_dir, mdc_mm: float | None = None, mesh_ply=None,
                        indices: dict | None = None) -> dict:
    """The deformation map of a ``torsoscan compare`` output folder (reads ``deformation.ply``).

    ``mesh_ply``: the later reconstruction's ``torso-mesh.ply`` (its own frame: moved into the earlier one by
    the folder's ``report.json`` transform). ``indices``: the earlier torso's ``torso-indices/1`` report, whose
    frame and vertebra prominens set the views and the trunk (arms, neck and head masked); without it the
    later torso is analysed here for them.
    """
    import json

    from recon_engine.surface import read_ply

    folder = Path(comparison_dir)
    ply = read_ply(folder / "deformation.ply")
    points, normals = ply["points"], ply.get("normals")
    d = ply["data"]["deformation_mm"]
    mesh = read_mesh(mesh_ply)
    if mesh is not None:
        try:
            tr = json.loads((folder / "report.json").read_text())["transform"]
            R, t = np.array(tr["R"], float), np.array(tr["t"], float)
            mesh = (mesh[0] @ R.T + t, mesh[1])
        except (OSError, ValueError, KeyError, TypeError):
            mesh = None  # where the mesh lies in the earlier frame is not known: the points are drawn
    frame, lm = frame_from_report(indices), landmarks_from_report(indices)
    if frame is None or "vertebra_prominens" not in lm:
        frame, lm = _own_frame(points, normals)
    png = deformation_picture(points, d, Path(out_dir) / "deformation.png", frame, mdc_mm=mdc_mm,
                              normals=normals, mesh=mesh, landmarks=lm)
    return {"deformation": png}


def _own_frame(points, normals):
    """The patient frame and landmarks of a torso given as points (its own analysis), or the shape's frame."""
    from .indices import analyse_torso
    from .torso import make_torso

    try:
        a = analyse_torso(make_torso(points, normals))
        return a.frame, a.landmarks
    except ValueError:
        return default_frame(points), {}
