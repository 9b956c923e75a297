"""The pictures are shaded surfaces with a fixed clinical colour scale (issue 28 §1).

Torsos and maps are drawn as filled, shaded surfaces (the mesh when given,
else a triangulation of the points), not scattered points; the deformation
map's scale is the same for every comparison, a change within the MDC is grey,
the arms, neck and head are masked grey, and the patient's L and R are on
their own sides of each view.
"""

import numpy as np
import pytest
from matplotlib.image import imread

from analysis import pictures
from analysis.frame import frame_from_posterior
from analysis.synthetic import synthetic_back
from analysis.torso import Torso, estimate_normals, orient_outward

SIZE = (900, 600)  # the maps' test size: three panels of 250 x 476 pixels from (0, 60), colour bar on the right
PANEL_W, TOP, PANEL_H = 250, 60, 476


@pytest.fixture(scope="module")
def trunk():
    t, truth = synthetic_back(rotation_deg=8.0, spacing_mm=8.0)
    return t, truth


def _frame(points):
    # the synthetic torso faces -Y with its left towards +X: posterior +Y
    return frame_from_posterior([0.0, 1.0, 0.0], np.median(points, axis=0))


def _arms(truth, spacing=8.0):
    """Two arms hanging 65 mm clear of the trunk's sides (the trunk is 150 mm half-wide), points and normals."""
    pts, nrm = [], []
    th = np.arange(0, 2 * np.pi, spacing / 35.0)
    for xc in (-250.0, 250.0):
        for z in np.arange(truth["sacral_point_z"] + 150.0, truth["vertebra_prominens_z"] - 20.0, spacing):
            n = np.column_stack([np.cos(th), np.sin(th), np.zeros_like(th)])
            pts.append(np.column_stack([xc + 35.0 * n[:, 0], 35.0 * n[:, 1], np.full(len(th), z)]))
            nrm.append(n)
    return np.vstack(pts), np.vstack(nrm)


def _png(path):
    img = imread(str(path))
    return img[..., :3]


def _covered(rgb):
    return rgb.min(axis=2) < 0.96


def _grey(rgb):
    return (rgb.max(axis=-1) - rgb.min(axis=-1)) < 0.05


def _red(rgb):
    return (rgb[..., 0] - rgb[..., 2]) > 0.15


def _panel(rgb, k):
    return rgb[TOP:TOP + PANEL_H, k * PANEL_W:(k + 1) * PANEL_W]


def test_it_draws_a_torso_as_a_filled_shaded_surface(trunk, tmp_path):
    torso, _ = trunk
    (back,) = pictures.torso_views(torso, tmp_path, _frame(torso.points), size=(300, 400), views=("back",))
    rgb = _png(back)
    cov = _covered(rgb)
    rows = np.nonzero(cov[:, 60:240].any(axis=1))[0]
    lo, hi = rows.min(), rows.max()
    # within the trunk's middle, every row is filled from one edge of the silhouette to the other: a cloud of
    # scattered points (8 mm apart here) leaves the background showing between them
    fill = []
    for r in range(lo + (hi - lo) // 4, hi - (hi - lo) // 4):
        c = np.nonzero(cov[r])[0]
        c = c[(c > 40) & (c < 260)]
        fill.append(cov[r, c.min():c.max() + 1].mean())
    assert min(fill) > 0.98
    # shaded: the light falls off towards the flanks, smoothly (neighbouring pixels differ little)
    lum = rgb[lo + (hi - lo) // 4:hi - (hi - lo) // 4, 60:240].mean(axis=2)
    inside = cov[lo + (hi - lo) // 4:hi - (hi - lo) // 4, 60:240]
    assert np.ptp(lum[inside]) > 0.15
    step = np.abs(np.diff(lum, axis=1))[inside[:, 1:] & inside[:, :-1]]
    assert np.median(step) < 0.02


def _cylinder(z0, z1, radius=100.0):
    """A triangle mesh of an open cylinder about the z axis, wound outwards: (vertices, faces)."""
    th = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    zs = np.arange(z0, z1 + 1.0, 20.0)
    V = np.array([[radius * np.cos(a), radius * np.sin(a), z] for z in zs for a in th])
    n_a = len(th)
    F = []
    for i in range(len(zs) - 1):
        for j in range(n_a):
            a, b, c, d = i * n_a + j, i * n_a + (j + 1) % n_a, (i + 1) * n_a + j, (i + 1) * n_a + (j + 1) % n_a
            F += [[a, b, d], [a, d, c]]
    return V, np.array(F)


def test_it_draws_the_reconstructions_mesh_when_given(tmp_path):
    # a cloud on a cylinder 400 mm tall, its mesh 600 mm tall: the picture's silhouette is the mesh's
    V, F = _cylinder(0.0, 600.0)
    pts = V[V[:, 2] <= 400.0]
    torso = Torso(pts, orient_outward(pts, estimate_normals(pts)))
    frame = frame_from_posterior([0.0, 1.0, 0.0], [0.0, 0.0, 300.0])
    (with_mesh,) = pictures.torso_views(torso, tmp_path / "m", frame, size=(300, 400), views=("back",), mesh=(V, F))
    (points_only,) = pictures.torso_views(torso, tmp_path / "p", frame, size=(300, 400), views=("back",))

    def aspect(path):
        rgb = _png(path)
        skin = _covered(rgb) & (rgb[..., 0] - rgb[..., 2] > 0.08)  # the surface, not the words
        r, c = np.nonzero(skin)
        return (np.ptp(r) + 1) / (np.ptp(c) + 1)

    assert aspect(with_mesh) == pytest.approx(3.0, rel=0.1)  # 600 mm tall, 200 mm wide
    assert aspect(points_only) == pytest.approx(2.0, rel=0.1)


def test_it_draws_a_comparisons_map_on_the_later_mesh_moved_into_the_earlier_frame(tmp_path):
    import json

    from recon_engine.surface import write_ply

    # the later torso's points in the earlier frame: a cylinder from 0 to 400 mm; its mesh in its own (later)
    # frame 100 mm lower: the comparison's transform (x_earlier = x_later + (0, 0, 100)) puts it over them
    V, F = _cylinder(0.0, 400.0)
    folder = tmp_path / "comparison"
    folder.mkdir()
    write_ply(folder / "deformation.ply", V, V * [1, 1, 0] / 100.0, None,
              {"deformation_mm": np.full(len(V), 6.0, np.float32)})
    (folder / "report.json").write_text(json.dumps({"transform": {"R": np.eye(3).tolist(), "t": [0, 0, 100]}}))
    write_ply(tmp_path / "later-mesh.ply", V - [0, 0, 100], None, F)
    indices = {"frame": {"origin_mm": [0, 0, 0], "left": [1, 0, 0], "posterior": [0, 1, 0], "up": [0, 0, 1]},
               "landmarks": {"vertebra_prominens": {"position_mm": [0, 100, 450]}}}
    png = pictures.comparison_pictures(folder, tmp_path / "out", mdc_mm=0.5, mesh_ply=tmp_path / "later-mesh.ply",
                                       indices=indices)["deformation"]
    back = _panel(_png(png), 0)
    red = _red(back) & _covered(back)
    rows, cols = np.nonzero(red)
    # the whole cylinder red (6 mm out) and 400 mm tall for 200 mm wide: mesh and points coincide
    assert (np.ptp(rows) + 1) / (np.ptp(cols) + 1) == pytest.approx(2.0, rel=0.08)
    assert red[rows.min():rows.max() + 1, cols.min():cols.max() + 1].mean() > 0.97


def test_it_draws_the_landmarks_and_the_symmetry_line_on_the_back(trunk, tmp_path):
    torso, truth = trunk
    P = torso.points

    def on_back(z):
        near = np.abs(P[:, 2] - z) < 6
        k = np.nonzero(near)[0][np.argmax(P[near, 1] - 0.2 * np.abs(P[near, 0]))]
        return P[k]

    vp_z, sp_z = truth["vertebra_prominens_z"], truth["sacral_point_z"]
    lms = {"vertebra_prominens": on_back(vp_z), "sacral_point": on_back(sp_z)}
    line = np.array([on_back(z) for z in np.linspace(sp_z + 30, vp_z - 30, 12)])
    back, side = pictures.torso_views(torso, tmp_path, _frame(P), size=(300, 400), views=("back", "side"),
                                      landmarks=lms, symmetry_line=line)
    rgb = _png(back)
    marker = (rgb[..., 0] > 0.9) & (rgb[..., 1] > 0.75) & (rgb[..., 2] < 0.45)  # the landmarks' yellow
    blue = (rgb[..., 2] > 0.6) & (rgb[..., 0] < 0.25)  # the line of symmetry
    assert marker.sum() > 40 and blue.sum() > 60
    # the line runs up the middle of the back, between the two markers
    r, c = np.nonzero(blue[:330])  # above the legend
    assert np.ptp(r) > 150 and abs(np.median(c) - 150) < 25
    # the line is on the back view only
    assert ((_png(side)[..., 2] > 0.6) & (_png(side)[..., 0] < 0.25)).sum() < 60


def test_it_uses_one_colour_scale_for_every_comparison(trunk, tmp_path):
    torso, _ = trunk
    P, frame = torso.points, _frame(torso.points)
    left = P[:, 0] > 0  # the patient's left (+X)
    small = np.where(left, 3.0, 1.0)  # this comparison's largest change: 3 mm
    large = np.where(left, 3.0, 9.0)  # this one's: 9 mm
    a = _png(pictures.deformation_picture(P, small, tmp_path / "a.png", frame, size=SIZE, normals=torso.normals))
    b = _png(pictures.deformation_picture(P, large, tmp_path / "b.png", frame, size=SIZE, normals=torso.normals))
    pa, pb = _panel(a, 0), _panel(b, 0)  # seen from the back: the patient's left is on the picture's left
    cov = _covered(pa) & _covered(pb)
    # the same 3 mm comes out in the same colour in both, though one map's values go three times as far
    same = np.abs(pa - pb).max(axis=2) < 1e-6
    left_half = cov.copy()
    left_half[:, 110:] = False
    left_half[:60] = False  # below the L mark
    assert left_half.sum() > 2000 and same[left_half].mean() > 0.97
    right_half = cov.copy()
    right_half[:, :140] = False
    assert same[right_half].mean() < 0.5
    # the colour bar states the fixed scale, its units and its sign
    assert pictures.DEFORMATION_LIMIT_MM == 10.0
    assert "mm" in pictures.DEFORMATION_BAR and "+ outwards" in pictures.DEFORMATION_BAR


def test_it_greys_a_change_within_the_mdc(trunk, tmp_path):
    torso, _ = trunk
    P = torso.points
    d = np.where(P[:, 0] > 0, 0.3, 5.0)  # the patient's left within the MDC (0.5 mm), the right beyond it
    rgb = _panel(_png(pictures.deformation_picture(P, d, tmp_path / "m.png", _frame(P), mdc_mm=0.5, size=SIZE,
                                                   normals=torso.normals)), 0)
    cov = _covered(rgb)
    cov[:60] = False
    left, right = cov.copy(), cov.copy()
    left[:, 110:] = False
    right[:, :140] = False
    assert _grey(rgb[left]).mean() > 0.97
    assert _red(rgb[right]).mean() > 0.97


def test_it_greys_the_arms_neck_and_head(trunk, tmp_path):
    torso, truth = trunk
    ap, an = _arms(truth)
    P = np.vstack([torso.points, ap])
    N = np.vstack([torso.normals, an])
    frame = _frame(torso.points)
    vp = np.array([0.0, 60.0, truth["vertebra_prominens_z"]])
    d = np.full(len(P), 6.0)  # the whole surface 6 mm out: the trunk red, what is masked grey
    masked = _panel(_png(pictures.deformation_picture(P, d, tmp_path / "arms.png", frame, size=SIZE, normals=N,
                                                      landmarks={"vertebra_prominens": vp})), 0)
    unmasked = _panel(_png(pictures.deformation_picture(P, d, tmp_path / "all.png", frame, size=SIZE, normals=N,
                                                        trunk=np.ones(len(P), bool))), 0)
    for rgb, arms_grey in ((masked, True), (unmasked, False)):
        cov = _covered(rgb)
        rows = np.nonzero(cov[:, 90:160].any(axis=1))[0]  # the middle columns: the neck and trunk, no words
        top, bottom = rows.min(), rows.max()
        mid = (top + bottom) // 2
        cols = np.nonzero(cov[mid])[0]
        outer = np.r_[cols.min() + 2:cols.min() + 6, cols.max() - 5:cols.max() - 1]  # the arms, at mid-height
        assert _grey(rgb[mid, outer]).all() == arms_grey
        centre = (cols.min() + cols.max()) // 2
        assert _red(rgb[mid, centre - 10:centre + 10]).all()  # the trunk, coloured either way
        neck = rgb[top + 3, centre - 3:centre + 3]  # above the vertebra prominens
        assert _grey(neck).all() == arms_grey


def test_it_marks_the_patients_left_and_right_on_their_own_sides(trunk):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    torso, _ = trunk
    P = torso.points
    frame = _frame(P)
    d = np.where(P[:, 0] > 40, 6.0, 0.0)  # a change on the patient's left only (+X in this torso)
    fig = pictures.deformation_figure(P, d, frame, mdc_mm=0.5, size=SIZE, normals=torso.normals)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3] / 255.0
    H = rgb.shape[0]
    axes = {ax.get_gid(): ax for ax in fig.axes}
    for k, view in enumerate(("back", "side", "front")):
        ax = axes[f"view-{view}"]
        box = ax.get_window_extent(renderer)
        marks = {t.get_gid(): t.get_window_extent(renderer) for t in ax.texts
                 if (t.get_gid() or "").startswith("side-")}
        if view == "side":
            assert marks == {}  # the side view shows one side only
            continue
        panel = rgb[int(H - box.y1):int(H - box.y0), int(box.x0):int(box.x1)]
        red = _red(panel) & _covered(panel)
        red[:60] = False
        red_x = box.x0 + np.nonzero(red)[1].mean()
        centre = 0.5 * (box.x0 + box.x1)
        # the change on the patient's left shows on the side the L is written on; R opposite
        l_x, r_x = 0.5 * (marks["side-L"].x0 + marks["side-L"].x1), 0.5 * (marks["side-R"].x0 + marks["side-R"].x1)
        assert np.sign(red_x - centre) == np.sign(l_x - centre) == -np.sign(r_x - centre)
        # seen from behind the patient's left is on the picture's left; from the front, on its right
        assert (l_x < centre) == (view == "back")
