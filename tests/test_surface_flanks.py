"""The arm surface keeps the torso's flanks, which the arm's mean view sees edge-on."""

from types import SimpleNamespace

import numpy as np

from recon_engine.surface import flank_faces, make_surface, off_surface, off_surface_again, small_components


def _arc_cameras(n=5, radius=2500.0, spacing=800.0):
    """Cameras on an arc around the vertical axis, aimed at it (world→camera rows: x right, y down, z forward)."""
    step = spacing / radius
    cams = []
    for a in (np.arange(n) - (n - 1) / 2) * step:
        C = radius * np.array([np.cos(a), np.sin(a), 0.0])
        z = -C / np.linalg.norm(C)
        y = np.array([0.0, 0.0, -1.0])
        cams.append(SimpleNamespace(R=np.vstack([np.cross(y, z), y, z]), C=C))
    return cams


def _cylinder(max_azimuth_deg=100.0, radius=150.0, spacing=3.0):
    """Points (mm) on a vertical cylinder facing the arc, from -max to +max azimuth, about ``spacing`` apart."""
    az = np.radians(np.arange(-max_azimuth_deg, max_azimuth_deg, np.degrees(spacing / radius)))
    h = np.arange(-150.0, 150.0, spacing)
    A, H = np.meshgrid(az, h)
    rng = np.random.default_rng(0)
    A = A + rng.uniform(-0.2, 0.2, A.shape) * spacing / radius  # not a perfect grid: Delaunay has ties otherwise
    return np.column_stack([radius * np.cos(A.ravel()), radius * np.sin(A.ravel()), H.ravel()])


def test_points_on_the_flanks_join_the_skin_instead_of_counting_as_islands():
    cams = _arc_cameras()
    P = _cylinder()
    azimuth = np.degrees(np.arctan2(P[:, 1], P[:, 0]))
    surface = make_surface(P, cams)
    in_tin = np.zeros(len(P), bool)
    in_tin[surface.faces.ravel()] = True
    flank = np.abs(azimuth) > 80
    # the arm's TIN (from its mean view) leaves out the skin that turns more than about 80 deg away from it:
    # by the TIN alone, all of it would be dropped as islands
    assert in_tin[flank].mean() < 0.05
    assert small_components(len(P), surface.faces, 10)[flank].all()
    flanks = flank_faces(surface.points, surface.faces, cams)
    assert len(flanks) and (~in_tin[flanks]).any(axis=1).all()  # each flank patch holds a left-out point
    island = small_components(len(P), np.concatenate([surface.faces, flanks]), 10)
    assert not island.any()


def test_wrong_matches_off_the_flank_stay_islands():
    cams = _arc_cameras()
    P = _cylinder()
    # a few wrong matches that agree with each other, 30 mm off the skin on the flank
    a = np.radians(np.array([95.0, 95.8, 96.6, 95.4, 96.2]))
    wrong = np.column_stack([180.0 * np.cos(a), 180.0 * np.sin(a), [0.0, 1.5, 0.0, 3.0, 3.0]])
    X = np.concatenate([P, wrong])
    surface = make_surface(X, cams)
    flanks = flank_faces(surface.points, surface.faces, cams)
    island = small_components(len(X), np.concatenate([surface.faces, flanks]), 10)
    assert island[len(P):].all()
    assert not island[:len(P)].any()


def test_it_adds_nothing_when_the_tin_holds_every_point():
    cams = _arc_cameras()
    P = _cylinder(max_azimuth_deg=40.0)
    surface = make_surface(P, cams)
    assert len(np.unique(surface.faces)) == len(P)
    assert flank_faces(surface.points, surface.faces, cams).shape == (0, 3)


def test_a_point_whose_wrong_neighbours_were_dropped_is_tested_again_against_the_skin():
    rng = np.random.default_rng(3)
    g = np.arange(0, 60, 1.5)
    skin = np.column_stack([*(a.ravel() for a in np.meshgrid(g, g)), rng.normal(0, 0.02, len(g) ** 2)])
    # wrong matches that agree with each other, 7 mm off the skin: each one's neighbours are the others
    wrong = np.column_stack([30 + rng.normal(0, 0.4, (14, 2)), 7 + rng.normal(0, 0.02, 14)])
    points = np.concatenate([skin, wrong])
    first = off_surface(points)
    assert not first["off"][len(skin):].any()  # their own plane: the first test cannot see them
    # the island of wrong matches dropped but one (joined to the skin by a flank's patch, say)
    kept = np.concatenate([np.arange(len(skin)), [len(skin)]])
    last = len(kept) - 1
    again = off_surface_again(points[kept], np.array([last, 0, 100]), first["limits"])
    assert again.tolist() == [True, False, False]
