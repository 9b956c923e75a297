"""The arm surface refined on local quadrics: onto the skin's local shape, and out of the matching window's
curvature and obliquity biases (recon_engine.surface.local_quadrics, window_curvature_bias, window_obliquity_bias;
reconstruction.refine_on_local_quadrics)."""

from dataclasses import dataclass, replace

import numpy as np
import pytest

from recon_engine.reconstruction import ReconstructionConfig, refine_on_local_quadrics
from recon_engine.surface import PointSurface, local_quadrics, window_curvature_bias, window_obliquity_bias

R_MM = 120.0  # a trunk's radius


@dataclass
class _Camera:  # what window_curvature_bias reads of a camera
    C: np.ndarray
    fx: float
    fy: float


def _sphere_cap(n=6000, seed=0):
    """Points on a sphere of radius R_MM about the origin, within 60 mm of its pole at +z (the cameras' side),
    about 1.4 mm apart; outward normals."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-60, 60, (4 * n, 2))
    xy = xy[np.hypot(*xy.T) < 60][:n]
    z = np.sqrt(R_MM ** 2 - np.sum(xy ** 2, axis=1))
    P = np.column_stack([xy, z])
    return P, P / R_MM


CAMERAS = [_Camera(np.array([dx, 0.0, 2500.0]), 2500.0, 2500.0) for dx in (-300.0, 0.0, 300.0)]


def test_it_recovers_the_curvature_of_a_sphere():
    P, N = _sphere_cap()
    q = local_quadrics(P, N)
    inner = np.hypot(P[:, 0], P[:, 1]) < 45  # away from the cap's rim
    # z = -(x² + y²) / (2 R) about each point: c3 + c5 = -1 / R
    assert np.median(q[inner, 3] + q[inner, 5]) == pytest.approx(-1 / R_MM, rel=0.02)
    assert np.max(np.abs(q[inner, 0])) < 1e-3  # the points lie on their quadric


def test_the_window_bias_is_the_windows_second_moment_times_the_curvature():
    P, N = _sphere_cap()
    q = local_quadrics(P, N)
    b = window_curvature_bias(q, P, CAMERAS, 9)
    g = np.linalg.norm(P - np.mean([c.C for c in CAMERAS], axis=0), axis=1) / 2500.0
    expected = -1 / R_MM * 81 / 12 * g ** 2  # about -0.054 mm at 1 mm per pixel: inside the bulging skin
    inner = np.hypot(P[:, 0], P[:, 1]) < 45
    np.testing.assert_allclose(b[inner], expected[inner], rtol=0.03)
    assert np.all(b[inner] < 0)


def _surface(P, N, sigma):
    return PointSurface(P, N, np.zeros((0, 3), np.int64), {"sigma_mm": np.full(len(P), sigma, np.float32)})


def test_it_moves_points_matched_inside_a_bulge_back_onto_it_and_averages_their_noise():
    P, N = _sphere_cap()
    rng = np.random.default_rng(1)
    cfg = ReconstructionConfig()
    q = local_quadrics(P, N)
    bias = window_curvature_bias(q, P, CAMERAS, cfg.tracking.matching.lsm_window)
    noise = rng.normal(0, 0.05, len(P))
    measured = P + (bias + noise)[:, None] * N  # as area-based matching delivers them
    surface = _surface(measured, N, 0.1)
    before = measured.copy()
    refined, shift = refine_on_local_quadrics(surface, CAMERAS, cfg)
    np.testing.assert_array_equal(surface.points, before)  # the input is not modified
    radial = lambda X: np.linalg.norm(X, axis=1) - R_MM  # noqa: E731
    inner = np.hypot(P[:, 0], P[:, 1]) < 45
    assert np.mean(radial(measured)[inner]) < -0.04
    assert abs(np.mean(radial(refined.points)[inner])) < 0.01  # the bias is gone
    rms = lambda r: float(np.sqrt(np.mean(r[inner] ** 2)))  # noqa: E731
    assert rms(radial(refined.points)) < 0.5 * rms(radial(measured))
    # each part on its own does what it says
    onto, _ = refine_on_local_quadrics(surface, CAMERAS, replace(cfg, window_curvature_correction=False))
    assert abs(np.mean(radial(onto.points)[inner]) - np.mean(radial(measured)[inner])) < 0.01
    assert np.std(radial(onto.points)[inner]) < 0.5 * np.std(radial(measured)[inner])


def test_a_wrong_match_beside_a_point_does_not_carry_it_off():
    P, N = _sphere_cap()
    far = 5.0  # mm off the skin: a wrong match the surface filters missed
    blunder = int(np.argmin(np.hypot(P[:, 0], P[:, 1])))
    measured = P.copy()
    measured[blunder] += far * N[blunder]
    refined, shift = refine_on_local_quadrics(_surface(measured, N, 0.1), CAMERAS,
                                              replace(ReconstructionConfig(), window_curvature_correction=False))
    near = np.linalg.norm(P - P[blunder], axis=1) < 6
    near[blunder] = False
    assert np.max(np.abs(shift[near])) < 0.01  # its neighbours stay on the skin
    assert abs(shift[blunder]) <= 3 * 0.1 + 1e-6  # and itself moves no farther than three of its sigmas


def test_it_can_be_turned_off():
    P, N = _sphere_cap(500)
    s = _surface(P + 0.3 * N, N, 0.1)
    refined, shift = refine_on_local_quadrics(s, CAMERAS, replace(ReconstructionConfig(), local_quadric_neighbours=0))
    assert refined is s and not shift.any()


def test_the_obliquity_bias_is_nothing_facing_the_cameras_and_grows_with_the_obliquity():
    eye = np.mean([c.C for c in CAMERAS], axis=0)
    theta = np.radians([0.0, 30.0, 60.0, 75.0, 85.0])
    P = np.zeros((len(theta), 3))
    to = eye / np.linalg.norm(eye)  # from the origin to the cameras: +z
    N = np.column_stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)])  # tilted away from +z by theta
    assert to @ N[0] == pytest.approx(1.0)
    b = window_obliquity_bias(P, N, CAMERAS, 0.02)
    g = 2500.0 / 2500.0  # mm of skin per pixel: distance 2500 mm, principal distance 2500 px
    np.testing.assert_allclose(b[:4], -0.02 * g ** 2 * (1 / np.cos(theta[:4]) - 1), atol=1e-12)
    assert b[0] == 0.0 and b[2] == pytest.approx(-0.02)  # inside the skin by 0.02 mm at 60 degrees, 1 mm a pixel
    half = window_obliquity_bias(P, N, [replace(c, fx=5000.0, fy=5000.0) for c in CAMERAS], 0.02)
    np.testing.assert_allclose(half, b / 4, atol=1e-12)  # half the skin per pixel: a quarter of the bias
    assert b[4] == pytest.approx(b[3])  # capped at 75 degrees: a grazing normal is itself uncertain


def test_it_moves_obliquely_seen_points_out_of_their_bias_and_leaves_the_frontal_ones():
    # a trunk-like cylinder of radius R_MM about the y axis, seen from +z: the flanks turn away from the cameras
    rng = np.random.default_rng(2)
    phi = rng.uniform(-np.radians(70), np.radians(70), 8000)
    y = rng.uniform(-80, 80, 8000)
    P = np.column_stack([R_MM * np.sin(phi), y, R_MM * np.cos(phi)])
    N = np.column_stack([np.sin(phi), np.zeros_like(phi), np.cos(phi)])
    cfg = replace(ReconstructionConfig(), window_curvature_correction=False, obliquity_bias=0.05)
    bias = window_obliquity_bias(P, N, CAMERAS, cfg.obliquity_bias)
    measured = P + bias[:, None] * N
    refined, _ = refine_on_local_quadrics(_surface(measured, N, 0.1), CAMERAS, cfg)
    radial = lambda X: np.hypot(X[:, 0], X[:, 2]) - R_MM  # noqa: E731
    flank = np.abs(np.degrees(phi)) > 55
    inner = np.abs(y) < 60  # away from the patch's ends, where the quadric's neighbours are one-sided
    assert np.mean(radial(measured)[flank & inner]) < -0.025
    assert abs(np.mean(radial(refined.points)[flank & inner])) < 0.005  # out of its bias
    front = np.abs(np.degrees(phi)) < 15
    assert abs(np.mean(radial(refined.points)[front & inner])) < 0.002  # the frontal skin stays
    off, _ = refine_on_local_quadrics(_surface(measured, N, 0.1), CAMERAS, replace(cfg, obliquity_bias=0.0))
    assert np.mean(radial(off.points)[flank & inner]) < -0.025  # the setting turns it off
