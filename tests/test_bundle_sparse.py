"""The sparse bundle adjustment against the dense solver it replaced, and its damping's bounds (issue 29).

The reference is the dense solver as it was before: central-difference
Jacobian, the whole normal matrix dense, corners eliminated by a dense Schur
complement, and the covariance by inverting the whole normal matrix.
"""

import numpy as np
import pytest
import scipy.sparse as sp

from recon_engine import bundle
from recon_engine.bundle import CAM_NAMES, CAM_STEP, project_observations

POSE_STEP = np.array([1e-7, 1e-7, 1e-7, 1e-3, 1e-3, 1e-3])  # rad, mm: the steps the dense solver used
POINT_STEP = 1e-3  # mm


def _fd_jacobian(pb, cams, poses, points, free_cam, free_pose):
    """Central differences of whole projections, one parameter of every camera (pose, corner) at a time."""
    N, C = len(pb.uv), len(cams)
    nc = int(free_cam.sum())
    cols_cam = np.full((C, len(CAM_NAMES)), -1)
    cols_cam[:, free_cam] = np.arange(C)[:, None] * nc + np.arange(nc)
    base_pose = C * nc
    base_point = base_pose + 6 * int(free_pose.sum())
    rows, cols, vals = [], [], []
    for which, steps in ((0, CAM_STEP), (1, POSE_STEP), (2, [POINT_STEP] * 3)):
        for j, h in enumerate(steps):
            if which == 0 and not free_cam[j]:
                continue
            args = [cams, poses, points]
            hi, lo = list(args), list(args)
            hi[which] = args[which].copy()
            lo[which] = args[which].copy()
            hi[which][:, j] += h
            lo[which][:, j] -= h
            d = (project_observations(*hi, pb.cam, pb.pose, pb.point)
                 - project_observations(*lo, pb.cam, pb.pose, pb.point)) / (2 * h)
            if which == 0:
                sel, col = np.ones(N, bool), cols_cam[pb.cam, j]
            elif which == 1:
                sel = free_pose[pb.pose]
                col = base_pose + (np.cumsum(free_pose) - 1)[pb.pose[sel]] * 6 + j
            else:
                sel, col = np.ones(N, bool), base_point + 3 * pb.point + j
            for a in (0, 1):
                rows.append(2 * np.flatnonzero(sel) + a)
                cols.append(col)
                vals.append(d[sel, a])
    n = base_point + 3 * len(points)
    J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(2 * N, n))
    return J, cols_cam, base_pose, base_point


def dense_reference(pb, max_iterations=30, reject_k=4.0, robust_rounds=4):
    cams, poses, points = pb.cams.astype(float), pb.poses.astype(float), pb.points.astype(float)
    survey = pb.points.astype(float)
    free_cam = np.array([n not in pb.fixed_iop for n in CAM_NAMES])
    free_pose = np.arange(len(poses)) > 0
    inlier = np.ones(len(pb.uv), bool)
    w_pt = 1 / pb.sigma_mm ** 2

    def step(dx, cams, poses, points, cols_cam, base_pose, base_point):
        cams, poses = cams.copy(), poses.copy()
        cams[cols_cam >= 0] += dx[cols_cam[cols_cam >= 0]]
        poses[1:] += dx[base_pose:base_point].reshape(-1, 6)
        return cams, poses, points + dx[base_point:].reshape(-1, 3)

    def normal(cams, poses, points, w_obs):
        J, cols_cam, base_pose, base_point = _fd_jacobian(pb, cams, poses, points, free_cam, free_pose)
        Nmat = (J.T.multiply(w_obs).tocsr() @ J).toarray()
        idx = base_point + np.arange(points.size)
        Nmat[idx, idx] += w_pt
        return J, Nmat, cols_cam, base_pose, base_point

    for round_ in range(robust_rounds + 1):
        w_obs = np.repeat(pb.weight * inlier, 2) / pb.sigma_px ** 2
        lam = 1e-3
        for _ in range(max_iterations):
            r = (pb.uv - project_observations(cams, poses, points, pb.cam, pb.pose, pb.point)).ravel()
            J, Nmat, cols_cam, base_pose, base_point = normal(cams, poses, points, w_obs)
            b = J.T.multiply(w_obs).tocsr() @ r
            b[base_point:] += w_pt * (survey - points).ravel()
            cost = float(r @ (w_obs * r) + w_pt * np.sum((survey - points) ** 2))
            diag = np.maximum(np.diag(Nmat), 1e-12)
            while True:
                M = Nmat + lam * np.diag(diag)
                # corners eliminated densely: 3x3 diagonal blocks
                na, q = base_point, len(points)
                idx = na + 3 * np.arange(q)[:, None] + np.arange(3)
                Dinv = np.linalg.inv(M[idx[:, :, None], idx[:, None, :]])
                B = M[:na, na:]
                BD = np.einsum("aqi,qij->aqj", B.reshape(na, q, 3), Dinv).reshape(na, -1)
                xa = np.linalg.solve(M[:na, :na] - BD @ B.T, b[:na] - BD @ b[na:])
                dx = np.concatenate([xa, np.einsum("qij,qj->qi", Dinv, (b[na:] - B.T @ xa).reshape(q, 3)).ravel()])
                new = step(dx, cams, poses, points, cols_cam, base_pose, base_point)
                r_new = (pb.uv - project_observations(*new, pb.cam, pb.pose, pb.point)).ravel()
                cost_new = float(r_new @ (w_obs * r_new) + w_pt * np.sum((survey - new[2]) ** 2))
                if cost_new <= cost or lam > 1e8:
                    break
                lam *= 10
            if cost_new <= cost:
                cams, poses, points = new
                lam = max(lam / 10, 1e-9)
            if cost - cost_new < 1e-10 * max(cost, 1.0) or (np.abs(dx[:base_pose]).max() < 1e-7
                                                            and np.abs(dx).max() < 1e-6):
                break
        res = pb.uv - project_observations(cams, poses, points, pb.cam, pb.pose, pb.point)
        dof = 2 * inlier.sum() - (len(Nmat) - points.size)
        sigma0 = np.sqrt((np.sum(pb.weight[inlier, None] * res[inlier] ** 2) / pb.sigma_px ** 2
                          + np.sum((survey - points) ** 2) * w_pt) / dof)
        std_res = np.linalg.norm(res, axis=1) * np.sqrt(pb.weight) / (pb.sigma_px * sigma0 * np.sqrt(2))
        bad = inlier & (std_res > reject_k)
        if not bad.any() or round_ == robust_rounds:
            break
        inlier &= ~(bad & (std_res > max(reject_k, 0.5 * std_res[bad].max())))
    w_obs = np.repeat(pb.weight * inlier, 2) / pb.sigma_px ** 2
    _, Nmat, cols_cam, base_pose, base_point = normal(cams, poses, points, w_obs)
    sd = np.sqrt(np.diag(np.linalg.inv(Nmat))) * sigma0  # the whole normal matrix inverted
    cam_sigma = np.zeros_like(cams)
    cam_sigma[cols_cam >= 0] = sd[cols_cam[cols_cam >= 0]]
    return {"cams": cams, "poses": poses, "points": points, "sigma0": sigma0, "inlier": inlier,
            "cam_sigma": cam_sigma, "point_sigma": sd[base_point:].reshape(-1, 3)}


@pytest.fixture(scope="module")
def first_pass(rig_session_1):
    """The bundle-adjustment problem of the first calibration pass of the tiny rig, and the sparse solution."""
    from recon_engine.calibration import calibrate
    from recon_engine.formats import read_capture, read_rig, read_testfield

    rig = read_rig(rig_session_1 / "rig.json")
    caps = [read_capture(p, rig) for p in sorted((rig_session_1 / "captures").glob("testfield-pose*"))]
    seen = []
    adjust = bundle.adjust

    def record(pb, **kw):
        seen.append((pb, adjust(pb, **kw)))
        return seen[-1][1]

    bundle.adjust = record
    try:
        calibrate(caps, rig, read_testfield(rig_session_1 / "testfield.json"))
    finally:
        bundle.adjust = adjust
    return seen[0]


def test_the_sparse_solver_gives_the_dense_solvers_result(first_pass):
    pb, sol = first_pass
    ref = dense_reference(pb)
    assert sol.converged and sol.reason
    assert np.array_equal(sol.inlier, ref["inlier"]) and (~sol.inlier).sum() > 0  # the same blunders rejected
    assert sol.sigma0 == pytest.approx(ref["sigma0"], rel=1e-9)
    # both stop when the cost changes by less than 1e-10 relative: the iterates may differ by about
    # 1e-3 of a standard deviation there, far below any figure the calibration reports
    fixed = np.array([n in pb.fixed_iop for n in CAM_NAMES])
    sig = np.where(fixed, 0.0, ref["cam_sigma"])
    assert np.all(np.abs(sol.cams - ref["cams"]) <= 1e-6 * np.abs(ref["cams"]) + 1e-3 * sig)
    assert np.all(np.abs(sol.points - ref["points"]) <= 1e-6 * np.abs(ref["points"]) + 1e-3 * ref["point_sigma"])
    assert np.allclose(sol.poses, ref["poses"], rtol=1e-6, atol=1e-6)
    # precision: the Schur-complement inverse equals the whole normal matrix's inverse
    assert np.allclose(sol.cam_sigma[:, ~fixed], ref["cam_sigma"][:, ~fixed], rtol=1e-5)
    assert np.allclose(sol.point_sigma, ref["point_sigma"], rtol=1e-5)


def test_the_analytic_jacobian_matches_central_differences(first_pass):
    pb, sol = first_pass
    free_cam = np.array([n not in pb.fixed_iop for n in CAM_NAMES])
    free_pose = np.arange(len(sol.poses)) > 0
    lay = bundle.layout(len(sol.cams), len(sol.poses), len(sol.points), free_cam, free_pose)
    J = bundle.jacobian(pb, sol.cams, sol.poses, sol.points, lay)
    F, *_ = _fd_jacobian(pb, sol.cams, sol.poses, sol.points, free_cam, free_pose)
    assert J.shape == F.shape and J.nnz == F.nnz
    scale = abs(F).max(axis=0).toarray().ravel()  # per unknown
    assert np.max(abs(J - F).max(axis=0).toarray().ravel() / scale) < 1e-6


def _small_problem(noise_px=0.05, seed=0):
    """A rig of 3 cameras round a 3-pose test field of 60 corners, simulated without images."""
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(-300, 300, 60), rng.uniform(-300, 300, 60), rng.uniform(-50, 50, 60)])
    cams = []
    for a in np.radians([-20, 0, 20]):
        C = np.array([2500 * np.sin(a), 0.0, -2500 * np.cos(a)])
        R = bundle.rodrigues(np.array([0.0, -a, 0.0]))  # looks at the origin
        cams.append([7450, 7450, 1500, 1000, -0.1, 0.2, 1e-4, -1e-4, 0, *bundle.rotation_to_rvec(R), *C])
    cams = np.array(cams)
    poses = np.array([[0, 0, 0, 0, 0, 0], [0, 0.3, 0, 40, 0, 0], [0.2, 0, 0.1, 0, -30, 20]], float)
    cam, pose, point = (g.ravel() for g in np.meshgrid(np.arange(3), np.arange(3), np.arange(60), indexing="ij"))
    uv = project_observations(cams, poses, points, cam, pose, point) + rng.normal(0, noise_px, (len(cam), 2))
    start = cams + np.r_[30, 30, 5, 5, 0.01, 0, 0, 0, 0, 1e-3, 1e-3, 1e-3, 5, 5, 5]
    return bundle.Problem(uv, cam, pose, point, np.ones(len(cam)), start, poses * 0.99, points, 0.05, 0.05)


def test_a_well_posed_problem_converges_and_says_why():
    sol = bundle.adjust(_small_problem())
    assert sol.converged and sol.reason in ("cost change below tolerance", "step below tolerance",
                                            "at the minimum: no step changes the cost beyond tolerance")
    assert 0.7 < sol.sigma0 < 1.3


def test_too_few_iterations_are_reported_as_not_converged():
    sol = bundle.adjust(_small_problem(), max_iterations=1, robust_rounds=0)
    assert not sol.converged and sol.reason == "iteration limit (1) reached"


def test_the_damping_gives_up_after_its_tries_and_says_so(monkeypatch):
    # a solver whose steps always raise the cost (a wrong sign): the damping loop must stop, not spin
    real = bundle.solve_normal
    calls = []

    def wrong_way(ne, lam):
        calls.append(lam)
        return -real(ne, lam)

    monkeypatch.setattr(bundle, "solve_normal", wrong_way)
    sol = bundle.adjust(_small_problem(), robust_rounds=0, max_damping_tries=5)
    assert len(calls) == 5 and calls[-1] == pytest.approx(1e-3 * 10 ** 4)
    assert not sol.converged and sol.reason.startswith("no step lowered the cost in 5 damping tries")


def test_a_system_without_a_finite_step_is_reported_not_looped_on():
    pb = _small_problem()
    pb.uv[:] = np.nan  # every step is NaN: no damping can help
    sol = bundle.adjust(pb, robust_rounds=0, max_damping_tries=4)
    assert not sol.converged
    assert sol.reason == "singular or non-finite normal equations in all 4 damping tries"
