"""The renderer: exact rays through the lens, shadows, determinism, noise."""

import numpy as np

from recon_engine.camera import Camera, project
from recon_engine.simulator.config import CameraConfig, ProjectorConfig
from recon_engine.simulator.render import Lighting, PreparedLighting, Scene, Surface, render
from recon_engine.simulator.rig import Projector, look_at


def _plane(z=0.0, size=2000.0, albedo=0.5):
    V = np.array([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]])
    T = np.array([[0, 1, 2], [0, 2, 3]])
    return Surface("skin", V, T, albedo=np.full(4, albedo))


def _box(centre, half):
    c = np.asarray(centre, float)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half + c
    faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    T = np.array([[f[0], f[1], f[2]] for f in faces] + [[f[0], f[2], f[3]] for f in faces])
    return Surface("wall", corners, T, albedo=np.full(8, 0.5))


def _camera(w=160, h=120, dist=(-0.2, 0.1, 0.001, -0.001, 0.0)):
    C = np.array([0.0, -300.0, 2000.0])
    return Camera(w, h, 400.0, 400.0, w / 2 + 3.3, h / 2 - 2.1, dist, look_at(C, [0, 0, 0], up=(0, 1, 0)), C)


CC = CameraConfig(width=160, height=120, pixel_size_mm=0.02, supersample=2, read_noise_e=0.0,
                  full_well_e=1e7, prnu=0.0, vignetting=False, focus_mm=2000.0, f_number=1e6)


def test_a_point_renders_where_the_camera_model_projects_it():
    # a small bright square on a dark plane lands at its projection
    cam = _camera()
    plane = _plane(albedo=0.05)
    sq = Surface("skin", np.array([[-20, -20, 1.0], [20, -20, 1.0], [20, 20, 1.0], [-20, 20, 1.0]]),
                 np.array([[0, 1, 2], [0, 2, 3]]), albedo=np.full(4, 0.9))
    img, _ = render(Scene([plane, sq]), cam, PreparedLighting(Lighting(ambient=1.0)), CC,
                    np.random.default_rng(0), exposure=0.9)
    ys, xs = np.nonzero(img > 100)
    w = img[ys, xs].astype(float)
    centroid = np.array([(xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()])
    expected = project(cam, [[0.0, 0.0, 1.0]])[0]
    assert np.linalg.norm(centroid - expected) < 0.2


def test_a_point_hidden_from_the_projector_is_in_shadow():
    cam = _camera()
    pc = ProjectorConfig(width=64, height=48, distance_mm=1500.0, coverage_mm=1500.0, black_level=0.0)
    P = np.array([0.0, 0.0, 1500.0])
    model = Camera(64, 48, 64.0, 64.0, 31.5, 23.5, np.zeros(5), look_at(P, [0, 0, 0], up=(0, 1, 0)), P)
    proj = Projector("P", "A", model, np.ones((48, 64), np.float32))
    occluder = _box([0.0, 0.0, 700.0], 60.0)  # between projector and plane
    lighting = PreparedLighting(Lighting(ambient=0.0, projectors=(proj,), projector_cfg=pc))
    scene = Scene([_plane(), occluder])
    img, _ = render(scene, cam, lighting, CC, np.random.default_rng(0), exposure=0.5)
    # (90, 0, 0) is seen by the camera past the box but hidden from the
    # projector straight above: the shadow of the box reaches |x| < 104 mm
    lit = project(cam, [[350.0, 0.0, 0.0]])[0]
    shadow = project(cam, [[90.0, 0.0, 0.0]])[0]
    assert img[int(round(lit[1])), int(round(lit[0]))] > 100
    assert img[int(round(shadow[1])), int(round(shadow[0]))] < 10


def test_same_seed_same_image_and_noise_is_there():
    cam = _camera()
    scene = Scene([_plane()])
    light = PreparedLighting(Lighting(ambient=1.0))
    noisy = CameraConfig(width=160, height=120, pixel_size_mm=0.02)
    a, _ = render(scene, cam, light, noisy, np.random.default_rng(4), exposure=0.5, prnu_seed=1)
    b, _ = render(scene, cam, light, noisy, np.random.default_rng(4), exposure=0.5, prnu_seed=1)
    c, _ = render(scene, cam, light, noisy, np.random.default_rng(5), exposure=0.5, prnu_seed=1)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    # shot noise of a uniform, well exposed plane: a few DN
    centre = a[40:80, 60:100].astype(float)
    assert 1.0 < centre.std() < 6.0
