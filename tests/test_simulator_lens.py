"""The simulator's own lens: forward model checked against OpenCV, exact inversion, rendering through it."""

from dataclasses import replace

import cv2
import numpy as np

from recon_engine.camera import Camera, project
from recon_engine.simulator import lens as L
from recon_engine.simulator.config import CameraConfig, engine_lens, preset
from recon_engine.simulator.render import Lighting, PreparedLighting, Scene, Surface, render
from recon_engine.simulator.rig import look_at, make_rig

# a strong lens with every term, at the paper's geometry (3000 x 2000 px, f = 7450 px)
RICH = L.Lens(7450.0, 7470.0, 1510.0, 990.0, k1=-0.22, k2=0.4, k3=-3.0, p1=4e-4, p2=-3e-4, p3=0.8,
              s1=1e-3, s2=-4e-3, s3=-8e-4, s4=3e-3, skew=0.6)


def _frame(lens, w=3000, h=2000, n=61):
    us, vs = np.meshgrid(np.linspace(-20, w + 20, n), np.linspace(-20, h + 20, n))
    return np.column_stack([us.ravel(), vs.ravel()])


def test_forward_model_is_opencvs_with_its_thin_prism_terms():
    lens = replace(RICH, p3=0.0, skew=0.0)
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-0.25, 0.25, (500, 2)), np.ones(500)])
    K = np.array([[lens.fx, 0, lens.cx], [0, lens.fy, lens.cy], [0, 0, 1.0]])
    dist12 = np.array([lens.k1, lens.k2, lens.p1, lens.p2, lens.k3, 0, 0, 0, lens.s1, lens.s2, lens.s3, lens.s4])
    cv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist12)
    ours = L.normalized_to_pixel(lens, X[:, :2])
    assert np.abs(ours - cv.reshape(-1, 2)).max() < 1e-6


def test_jacobian_is_the_derivative_of_the_forward_model():
    rng = np.random.default_rng(2)
    xy = rng.uniform(-0.3, 0.3, (200, 2))
    a, b, c, d = L.distort_jacobian(RICH, xy[:, 0], xy[:, 1])
    h = 1e-7
    dx = (L.distort(RICH, xy + [h, 0]) - L.distort(RICH, xy - [h, 0])) / (2 * h)
    dy = (L.distort(RICH, xy + [0, h]) - L.distort(RICH, xy - [0, h])) / (2 * h)
    for ours, num in ((a, dx[:, 0]), (b, dy[:, 0]), (c, dx[:, 1]), (d, dy[:, 1])):
        assert np.abs(ours - num).max() < 1e-7


def test_inversion_round_trips_to_a_billionth_of_a_pixel():
    uv = _frame(RICH)
    back = L.normalized_to_pixel(RICH, L.pixel_to_normalized(RICH, uv))
    assert np.abs(back - uv).max() < 1e-9
    # the renderer's path: a guess interpolated on the coarse grid, then one Newton step
    grid = L.inverse_grid(RICH, 3000, 2000, 8)
    rng = np.random.default_rng(3)
    uv = rng.uniform([-0.5, -0.5], [2999.5, 1999.5], (20000, 2))
    xy = L.pixel_to_normalized_fast(RICH, uv, grid, 8)
    assert np.abs(L.normalized_to_pixel(RICH, xy) - uv).max() < 2e-6
    xy = L.pixel_to_normalized_fast(RICH, uv, grid, 8, iterations=2)
    assert np.abs(L.normalized_to_pixel(RICH, xy) - uv).max() < 1e-9
    # rays and projection are inverse to each other too
    R = look_at([0, -2500, 1000], [0, 0, 1000])
    C = np.array([0.0, -2500.0, 1000.0])
    X = C + 2400.0 * L.rays(RICH, R, uv[:100])
    assert np.abs(L.project(RICH, R, C, X) - uv[:100]).max() < 1e-7


def test_a_point_renders_where_the_true_lens_projects_it_not_the_engine_model():
    # 160 x 120 px at f = 400 px: a thin prism large enough to move the point by over a pixel
    C = np.array([0.0, -300.0, 2000.0])
    R = look_at(C, [0, 0, 0], up=(0, 1, 0))
    cam = Camera(160, 120, 400.0, 400.0, 83.3, 57.9, (-0.2, 0.1, 0.001, -0.001, 0.0), R, C)
    lens = replace(L.Lens.from_camera(cam), fy=401.2, k3=0.5, s1=0.1, s3=-0.08, skew=0.3)
    cc = CameraConfig(width=160, height=120, pixel_size_mm=0.02, supersample=2, read_noise_e=0.0,
                      full_well_e=1e7, prnu=0.0, vignetting=False, focus_mm=2000.0, f_number=1e6)
    size = 2000.0
    plane = Surface("skin", np.array([[-size, -size, 0], [size, -size, 0], [size, size, 0], [-size, size, 0.0]]),
                    np.array([[0, 1, 2], [0, 2, 3]]), albedo=np.full(4, 0.05))
    X0 = np.array([250.0, -150.0, 1.0])  # off-centre, where the prism and k3 act
    sq = Surface("skin", X0 + np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0.0]]),
                 np.array([[0, 1, 2], [0, 2, 3]]), albedo=np.full(4, 0.9))
    img, _ = render(Scene([plane, sq]), cam, PreparedLighting(Lighting(ambient=1.0)), cc,
                    np.random.default_rng(0), exposure=0.9, lens=lens)
    ys, xs = np.nonzero(img > 100)
    w = img[ys, xs].astype(float)
    centroid = np.array([(xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()])
    expected = L.project(lens, R, C, [X0])[0]
    engine = project(cam, [X0])[0]
    assert np.linalg.norm(expected - engine) > 1.0
    assert np.linalg.norm(centroid - expected) < 0.2


def test_rig_lenses_are_richer_than_the_engine_model_and_the_old_draws_stay():
    cfg = preset("paper", seed=5)
    truth = make_rig(cfg, np.random.default_rng(7), 1100.0)
    old = make_rig(engine_lens(cfg), np.random.default_rng(7), 1100.0)
    lenses = list(truth.lenses.values())
    k3 = np.array([x.k3 for x in lenses])
    aspect = np.array([x.fy / x.fx - 1 for x in lenses])
    assert np.all(k3 != 0) and 0.5 < k3.std() < 3.0
    assert 5e-4 < np.abs(aspect).mean() < 5e-3 and np.abs(aspect).max() < 0.01
    assert all(x.has_extra_terms for x in lenses)  # the thin prism is on by default
    # the engine's view of each lens holds the true lens's own values of the terms it models
    for cam_id, lens in truth.lenses.items():
        cam = truth.cameras[cam_id]
        assert np.array_equal(cam.dist, lens.dist5) and (cam.fx, cam.fy) == (lens.fx, lens.fy)
        # same rig and the same old lens terms with the new terms off
        o = old.cameras[cam_id]
        assert np.array_equal(cam.C, o.C) and np.array_equal(cam.R, o.R)
        assert (cam.fx, cam.cx, cam.cy) == (o.fx, o.cx, o.cy) and np.array_equal(cam.dist[:4], o.dist[:4])
        assert o.dist[4] == 0.0 and not old.lenses[cam_id].has_extra_terms
    # the mild thin prism moves paper-scale image points by a few hundredths of a pixel
    res = [L.engine_residual_px(x, 3000, 2000)["max_px"] for x in lenses]
    assert 0.005 < np.median(res) < 0.3
