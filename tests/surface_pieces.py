"""Pieces of torso-like surface for the registration tests."""

import numpy as np

from recon_engine.surface import PointSurface, triangulate, vertex_normals


def torso_like(x0, x1, n=6000, noise=0.0, seed=0):
    """A curved, bumpy piece of surface (mm) between ``x0`` and ``x1``, seen from +z far away."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(x0, x1, n)
    y = rng.uniform(-200, 200, n)
    z = -x ** 2 / 600 - y ** 2 / 2000 + 8 * np.sin(x / 40) * np.cos(y / 55) + rng.normal(0, noise, n)
    P = np.column_stack([x, y, z])
    eye = np.array([0, 0, 3000.0])
    R = np.eye(3)
    R[2] = [0, 0, -1]
    R[1] = [0, -1, 0]
    F = triangulate(P, R, eye)
    return PointSurface(P, vertex_normals(P, F, eye), F)


def moved(surface, T):
    """``surface`` moved by the transform ``T`` (points and normals)."""
    return PointSurface(T.apply(surface.points), T.rotate(surface.normals), surface.faces)
