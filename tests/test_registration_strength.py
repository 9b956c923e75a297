"""Geometric strength of the multiple registration: an arm its overlaps do not hold is a failed torso."""

from types import SimpleNamespace

import numpy as np

from recon_engine.bundle import rodrigues
from recon_engine.reconstruction import register_arms
from recon_engine.registration import ICPatchConfig, Transform, arm_strength
from recon_engine.surface import PointSurface, triangulate, vertex_normals

ARMS = ("A", "B", "C", "D")


def _radius(theta, y, smooth_c):
    """A bumpy vertical cylinder (radius ~150 mm, axis y); optionally plain where arm C overlaps B and D."""
    bump = 6 * np.sin(5 * theta) * np.cos(y / 35) + 4 * np.cos(3 * theta + y / 50)
    if smooth_c:
        # arm C looks from 180 deg and sees 110-250 deg; its overlaps (110-160, 200-250 deg) are a plain
        # cylinder there, which leaves C free to slide along the axis and turn about it
        d = np.abs(np.degrees(theta) - 180.0)
        bump = bump * np.clip((np.abs(d - 45.0) - 25.0) / 10.0, 0.0, 1.0) * (d < 80) + bump * (d >= 80)
    return 150.0 + bump


def four_arm_surfaces(smooth_c, n=3000, noise=0.02, seed=0):
    """Each arm's surface in its own (displaced) frame, and the true displacements."""
    rng = np.random.default_rng(seed)
    surfaces, truth = {}, {}
    for k, arm in enumerate(ARMS):
        look = np.radians(90.0 * k)
        theta = look + np.radians(rng.uniform(-70, 70, n))
        y = rng.uniform(-150, 150, n)
        r = _radius(np.mod(theta, 2 * np.pi), y, smooth_c) + rng.normal(0, noise, n)
        P = np.column_stack([r * np.cos(theta), y, r * np.sin(theta)])
        eye = 1500.0 * np.array([np.cos(look), 0.0, np.sin(look)])
        z = -eye / np.linalg.norm(eye)
        R = np.array([np.cross([0.0, 1.0, 0.0], z), [0.0, 1.0, 0.0], z])
        F = triangulate(P, R, eye)
        N = vertex_normals(P, F, eye)
        # the arm moved: what it measured lies displaced from the body by D^-1
        D = (Transform.identity() if arm == "A" else
             Transform(1.0, rodrigues(np.radians([0.1, 0.5 * k, -0.1])), np.array([1.0, -2.0 * k, 1.5])))
        Di = D.inverse()
        surfaces[arm] = PointSurface(Di.apply(P), Di.rotate(N), F, {"sigma_mm": np.full(n, noise, np.float32)})
        truth[arm] = D
    return surfaces, truth


def register(surfaces, icpatch=None):
    from recon_engine.reconstruction import TorsoConfig

    rig = SimpleNamespace(arms=tuple(SimpleNamespace(id=a) for a in ARMS),
                          reference_arm=SimpleNamespace(id="A"))
    cal = SimpleNamespace(frame="test")
    cfg = TorsoConfig(icpatch=icpatch or ICPatchConfig())
    return register_arms(surfaces, {a: {} for a in surfaces}, {}, rig, cal, cfg)


def test_arms_held_by_bumpy_overlaps_are_ok():
    surfaces, truth = four_arm_surfaces(smooth_c=False)
    res = register(surfaces)
    rep = res["report"]
    assert rep["status"] == "ok", rep["problems"]
    for a in "BCD":
        st = rep["registration"]["strength"][a]
        assert st["position_sigma_mm"] < 0.1  # limit: 6 x the points' 0.02 mm = 0.12 mm
        err = res["transforms"][a].apply(surfaces[a].points) - truth[a].apply(surfaces[a].points)
        assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.4


def test_an_arm_its_overlaps_leave_free_fails_the_torso_and_is_named():
    surfaces, _ = four_arm_surfaces(smooth_c=True)
    rep = register(surfaces)["report"]
    assert rep["status"] == "failed"
    weak = [p for p in rep["problems"] if "not held" in p]
    assert weak and all(p.startswith("arm C ") for p in weak), rep["problems"]
    # the free directions of a plain cylinder about the vertical axis: along and about y
    st = rep["registration"]["strength"]["C"]
    assert abs(st["translation_direction"][1]) > 0.9 or abs(st["rotation_axis"][1]) > 0.9
    assert "mostly y" in weak[0]


def test_strength_of_a_known_covariance():
    cov = np.zeros((7, 7))
    cov[5, 5] = 0.3 ** 2  # ty: 0.3 mm
    cov[1, 1] = np.radians(0.01) ** 2  # omega: 0.01 deg
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0]])
    st = arm_strength(cov, pts, np.zeros(3))
    assert abs(st["translation_sigma_mm"] - 0.3) < 1e-9 and st["translation_direction"] == [0.0, 1.0, 0.0]
    assert abs(st["rotation_sigma_deg"] - 0.01) < 1e-9 and st["rotation_axis"] == [1.0, 0.0, 0.0]
    # at 100 mm from the centre the rotation adds 100 * 0.01 deg along y
    assert abs(st["position_sigma_mm"] - np.hypot(0.3, 100 * np.radians(0.01))) < 1e-9
