"""Least-squares multi-ray intersection with blunder rejection."""

import numpy as np

from recon_engine.camera import Camera
from recon_engine.multiview import IntersectionConfig, intersect


def _cameras(k=5):
    cams = []
    for i in range(k):
        az = np.radians(-40 + 20 * i)
        C = np.array([2500 * np.sin(az), -2500 * np.cos(az), 0.0])
        z = -C / np.linalg.norm(C)
        x = np.cross([0, 0, 1.0], z)
        x /= np.linalg.norm(x)
        R = np.vstack([x, np.cross(z, x), z])
        cams.append(Camera(3000, 2000, 7450, 7450, 1500 + 7 * i, 1000 - 5 * i, [-0.1, 0.2, 1e-4, -2e-4, 0], R, C))
    return cams


def _observe(cams, X, sigma, rng):
    obs = np.stack([c.project(X) for c in cams], axis=1)
    return obs + rng.normal(0, sigma, obs.shape)


def test_it_recovers_points_to_their_propagated_precision():
    rng = np.random.default_rng(0)
    cams = _cameras()
    X = rng.uniform(-150, 150, (2000, 3))
    res = intersect(cams, _observe(cams, X, 0.1, rng))
    assert res["valid"].mean() > 0.99
    err = res["X"][res["valid"]] - X[res["valid"]]
    # the errors agree with the covariance: mean squared Mahalanobis distance about 3
    m = np.einsum("ti,tij,tj->t", err, np.linalg.inv(res["cov"][res["valid"]]), err)
    assert 2.4 < m.mean() < 3.6
    # a 99.9% test on each ray: a few good rays are removed by chance, no more
    assert np.mean(res["rays"][res["valid"]] == 5) > 0.98


def test_it_removes_a_blundered_ray_and_keeps_the_point():
    rng = np.random.default_rng(1)
    cams = _cameras()
    X = rng.uniform(-150, 150, (200, 3))
    obs = _observe(cams, X, 0.05, rng)
    obs[:, 2, 0] += 4.0  # a wrong match in the middle image
    res = intersect(cams, obs)
    assert res["valid"].mean() > 0.98
    assert not res["used"][:, 2].any() and np.all(res["rays"] == 4)
    assert np.sqrt(np.mean(np.sum((res["X"] - X) ** 2, axis=1))) < 0.2


def test_two_inconsistent_rays_drop_the_point():
    cams = _cameras(2)
    X = np.array([[0.0, 0.0, 0.0]])
    obs = np.stack([c.project(X) for c in cams], axis=1)
    obs[0, 1, 1] += 3.0  # off the epipolar line: no point explains both rays
    res = intersect(cams, obs)
    assert not res["valid"][0] and res["reason"][0] == "inconsistent rays"


def test_points_with_one_ray_are_dropped_with_a_reason():
    cams = _cameras(3)
    obs = np.full((1, 3, 2), np.nan)
    obs[0, 0] = [1500, 1000]
    res = intersect(cams, obs)
    assert res["reason"][0] == "fewer than two rays"


def test_blocks_in_threads_give_the_same_points_as_one_block():
    rng = np.random.default_rng(4)
    cams = _cameras()
    X = rng.uniform(-150, 150, (3000, 3))
    obs = _observe(cams, X, 0.1, rng)
    obs[::7, 2] += 5.0  # blunders, so that rays are removed in both
    obs[::11, 4] = np.nan
    one = intersect(cams, obs, IntersectionConfig(threads=1))
    two = intersect(cams, obs, IntersectionConfig(threads=2))
    assert set(one) == set(two)
    for key in one:
        assert np.array_equal(np.asarray(one[key]), np.asarray(two[key])), key


def test_the_collinearity_jacobian_matches_central_differences():
    from recon_engine.multiview import project_with_jacobian

    rng = np.random.default_rng(5)
    cam = _cameras()[1]
    X = rng.uniform(-300, 300, (200, 3))
    uv, J = project_with_jacobian(cam, X)
    np.testing.assert_allclose(uv, cam.project(X), atol=1e-9)  # the same pixels as the camera model
    h = 1e-3  # mm
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        numeric = (cam.project(X + step) - cam.project(X - step)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], numeric, atol=1e-6)  # px/mm
