"""The camera model agrees with OpenCV and inverts exactly."""

import cv2
import numpy as np
import pytest

from recon_engine.camera import (
    Camera,
    opk_to_rotation,
    photogrammetric_iop,
    pixel_to_normalized,
    pixel_to_ray,
    project,
    rotation_to_opk,
)

MILD = [-0.08, 0.12, 0.0004, -0.0003, -0.05]
STRONG = [-0.35, 0.25, 0.002, -0.0015, -0.12]


def _camera(dist, seed=0):
    rng = np.random.default_rng(seed)
    R = cv2.Rodrigues(rng.normal(0, 0.4, 3))[0]
    return Camera(3000, 2000, 7450.2, 7451.9, 1512.3, 987.6, dist, R, rng.normal(0, 500, 3))


@pytest.mark.parametrize("dist", [MILD, STRONG, [0, 0, 0, 0, 0]])
def test_projection_agrees_with_opencv(dist):
    cam = _camera(dist)
    rng = np.random.default_rng(1)
    # points in front of the camera, spread over (and beyond) the frame
    xy = rng.uniform(-0.25, 0.25, (5000, 2))
    depth = rng.uniform(1500, 3500, 5000)
    X_cam = np.column_stack([xy * depth[:, None], depth])
    X = X_cam @ cam.R + cam.C  # camera→world
    ours = project(cam, X)
    theirs, _ = cv2.projectPoints(X.reshape(-1, 1, 3), cam.rvec, cam.tvec, cam.K, cam.dist)
    assert np.max(np.abs(ours - theirs.reshape(-1, 2))) < 1e-9


@pytest.mark.parametrize("dist", [MILD, STRONG])
def test_pixel_to_ray_round_trips_over_the_whole_frame(dist):
    cam = _camera(dist)
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 61), np.linspace(0, cam.height - 1, 41))
    uv = np.column_stack([u.ravel(), v.ravel()])
    # include the four extreme corners explicitly
    uv = np.vstack([uv, [[0, 0], [cam.width - 1, 0], [0, cam.height - 1], [cam.width - 1, cam.height - 1]]])
    rays = pixel_to_ray(cam, uv)
    X = cam.C + rays * 2500.0
    back = project(cam, X)
    assert np.max(np.linalg.norm(back - uv, axis=1)) < 1e-6


def test_strong_distortion_corners_beat_opencv_fixed_point():
    # cv2.undistortPoints with its default 5 iterations is visibly off in the
    # corners of a strongly distorted frame; ours must not be.
    cam = _camera(STRONG)
    uv = np.array([[0.0, 0.0], [cam.width - 1.0, cam.height - 1.0]])
    ours = pixel_to_normalized(cam, uv)
    back = project(cam.with_pose(np.eye(3), np.zeros(3)), np.column_stack([ours, np.ones(2)]))
    assert np.max(np.abs(back - uv)) < 1e-6


def test_opk_round_trip_and_known_values():
    for o, p, k in [(0, 0, 0), (10, -20, 30), (-45, 60, 170), (89, 5, -120)]:
        R = opk_to_rotation(o, p, k)
        assert np.allclose(R @ R.T, np.eye(3))
        assert np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(rotation_to_opk(R), [o, p, k])
    # a camera looking straight down the world -Z (nadir), image top towards +Y:
    # the classic photogrammetric zero rotation.
    R_nadir = np.diag([1.0, -1.0, -1.0])
    assert np.allclose(rotation_to_opk(R_nadir), [0, 0, 0])


def test_photogrammetric_iop_terms():
    cam = Camera(3000, 2000, 7446.8, 7446.8, 1509.5, 990.5)
    iop = photogrammetric_iop(cam, 0.0047)
    assert np.isclose(iop["principal_distance_mm"], 35.0, atol=1e-3)
    assert np.allclose(iop["principal_point_offset_px"], [10.0, -9.0])
    # photogrammetric y is up: a principal point above the centre is positive
    assert np.allclose(iop["principal_point_offset_mm"], [0.047, 0.0423])


def test_inputs_are_not_modified():
    cam = _camera(MILD)
    uv = np.array([[10.0, 20.0], [1500.0, 1000.0]])
    uv0 = uv.copy()
    pixel_to_ray(cam, uv)
    assert np.array_equal(uv, uv0)
    with pytest.raises(ValueError):
        cam.dist[0] = 1.0
