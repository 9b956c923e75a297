"""The display mesh bridges the measured skin's small gaps and leaves its wide gaps open.

A trim closer than the Poisson octree's own cell strewed pinholes over the skin
(paper scale, depth 9: 15 % of the vertices cut, most inside the measured skin).
"""
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from recon_engine.reconstruction import poisson_cell_mm, poisson_mesh


def _sphere_with_gaps(radius=50.0, n=60000, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    P = radius * u
    # a wide gap: a cap of 20 mm radius around +z; and 40 narrow gaps of 2 mm radius elsewhere
    keep = np.linalg.norm(P - [0, 0, radius], axis=1) > 20.0
    c = rng.normal(size=(200, 3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    c = radius * c[c[:, 2] < 0.3][:40]
    for centre in c:
        keep &= np.linalg.norm(P - centre, axis=1) > 2.0
    return P[keep], u[keep]


def _boundary_loops(V, F):
    """How many closed rims the mesh has (edges used by one face, grouped by shared vertices)."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    key, count = np.unique(E[:, 0] * len(V) + E[:, 1], return_counts=True)
    rim = key[count == 1]
    if len(rim) == 0:
        return 0
    a, b = rim // len(V), rim % len(V)
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(V), len(V)))
    n, labels = connected_components(g, directed=False)
    return len(np.unique(labels[np.unique(np.concatenate([a, b]))]))


def test_it_bridges_gaps_narrower_than_a_cell_and_keeps_the_wide_one_open():
    P, N = _sphere_with_gaps()
    depth = 5
    assert 3.0 < poisson_cell_mm(P, depth) < 4.0  # wider than the narrow gaps' radius (2 mm)
    V, F = poisson_mesh(P, N, depth, trim_mm=1.0, trim_cells=1.0)
    assert _boundary_loops(V, F) == 1  # the cap only
    # no vertex is left far out over the cap
    assert np.min(np.linalg.norm(V - [0, 0, 50.0], axis=1)) > 12.0


def test_a_trim_closer_than_a_cell_leaves_pinholes():
    P, N = _sphere_with_gaps()
    V, F = poisson_mesh(P, N, 5, trim_mm=1.0, trim_cells=0.0)
    assert _boundary_loops(V, F) > 10
