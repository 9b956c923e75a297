"""Self-calibrating bundle adjustment over a surveyed test field.

Unknowns
    per camera: IOPs ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` (px and OpenCV's
    unitless distortion terms) and EOPs (Rodrigues vector of R world→camera,
    perspective centre C in mm); cameras do not move between test-field poses;
    per test-field pose k ≥ 1: its rigid pose in the pose-0 frame
    (``X_world = R_k @ X_field + t_k``); pose 0 is the datum;
    per target corner: its coordinates in the test-field frame (mm), tied to the
    survey by weighted pseudo-observations (``sigma_mm``).
Observations
    image coordinates of target corners (px), weighted.

Gauss–Newton with Levenberg–Marquardt damping on the normal equations; the
Jacobian is sparse (every observation depends on one camera, one pose and one
point), is formed analytically from per-observation blocks and kept as a CSR
matrix. The corners (3 unknowns each, thousands of them)
are eliminated first from the sparse normal equations — their block is 3×3
block diagonal — leaving a small dense system of the cameras and poses
(14 unknowns per camera, 6 per pose: about 300 for a 20-camera rig) solved
directly. Blunders are removed by iterated rejection of standardized residuals;
precision comes from the inverse of the normal matrix scaled by the a
posteriori variance factor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .camera import distort_jacobian

IOP_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
EOP_NAMES = ("rx", "ry", "rz", "X", "Y", "Z")
CAM_NAMES = IOP_NAMES + EOP_NAMES
N_CAM = len(CAM_NAMES)
POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")

# central-difference steps per camera parameter (px, unitless, rad, mm): what numerical derivatives of
# a camera's projections use (the stability measures'); the adjustment's own Jacobian is analytic
CAM_STEP = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6, 1e-7, 1e-7, 1e-7, 1e-3, 1e-3, 1e-3])


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of Rodrigues vectors (..., 3), vectorized."""
    rvec = np.asarray(rvec, dtype=float)
    theta = np.linalg.norm(rvec, axis=-1)[..., None, None]
    small = theta < 1e-12
    k = rvec / np.where(small[..., 0], 1.0, theta[..., 0])
    K = np.zeros(rvec.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    R = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)
    return np.where(small, np.eye(3), R)


def rotation_to_rvec(R: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=float))[0].ravel()


@dataclass
class Problem:
    """Observations and initial values of a test-field bundle adjustment.

    Attributes
    ----------
    uv : (N, 2) image coordinates (px) of target corners
    cam, pose, point : (N,) int indices of each observation's camera, pose, corner
    weight : (N,) relative weights (1 = a corner of nominal precision)
    cams : (C, 15) initial camera parameters (:data:`CAM_NAMES`)
    poses : (P, 6) initial pose parameters; row 0 is the datum and stays zero
    points : (Q, 3) surveyed corner coordinates (mm, test-field frame)
    sigma_px : a priori standard deviation of an image coordinate
    sigma_mm : survey standard deviation of a corner coordinate
    fixed_iop : IOP names held at their initial values (e.g. ``("k3",)``)
    """

    uv: np.ndarray
    cam: np.ndarray
    pose: np.ndarray
    point: np.ndarray
    weight: np.ndarray
    cams: np.ndarray
    poses: np.ndarray
    points: np.ndarray
    sigma_px: float = 0.1
    sigma_mm: float = 0.05
    fixed_iop: tuple = ("k3",)


@dataclass
class Solution:
    cams: np.ndarray
    poses: np.ndarray
    points: np.ndarray
    residuals: np.ndarray  # (N, 2) px, observed - computed
    inlier: np.ndarray  # (N,) bool
    sigma0: float  # a posteriori standard deviation of unit weight
    cam_sigma: np.ndarray  # (C, 15)
    pose_sigma: np.ndarray  # (P, 6)
    point_sigma: np.ndarray  # (Q, 3)
    correlations: list = field(default_factory=list)  # (camera, name_a, name_b, rho) above the threshold
    iterations: int = 0
    converged: bool = False
    history: list = field(default_factory=list)
    cam_cov: np.ndarray | None = None  # (C, 15, 15) covariance of each camera's parameters (fixed ones zero)
    cams_cov: np.ndarray | None = None  # (C*15, C*15) joint covariance of all cameras' parameters (fixed ones zero)
    reason: str = ""  # how the last round's iterations ended (see :func:`adjust`)


def project_observations(cams, poses, points, cam, pose, point) -> np.ndarray:
    """Image coordinates (N, 2) of every observation for the given parameters."""
    c = cams[cam]
    Rp = rodrigues(poses[:, :3])[pose]  # one rotation per pose and camera, then gathered
    Xw = np.einsum("nij,nj->ni", Rp, points[point]) + poses[pose, 3:]
    Rc = rodrigues(cams[:, 9:12])[cam]
    xc = np.einsum("nij,nj->ni", Rc, Xw - c[:, 12:15])
    x = xc[:, 0] / xc[:, 2]
    y = xc[:, 1] / xc[:, 2]
    k1, k2, p1, p2, k3 = c[:, 4], c[:, 5], c[:, 6], c[:, 7], c[:, 8]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([c[:, 0] * xd + c[:, 2], c[:, 1] * yd + c[:, 3]])


@dataclass(frozen=True)
class Layout:
    """Where each free parameter sits in the vector of unknowns: cameras, then poses 1.., then points.

    ``cam_cols[c, j]`` is the column of camera ``c``'s parameter ``j`` (-1 when
    held fixed); pose ``k`` ≥ 1 has columns ``base_pose + 6 (k - 1) + (0..5)``;
    corner ``q`` has ``base_point + 3 q + (0..2)``.
    """

    cam_cols: np.ndarray  # (C, 15) int
    free_cam: np.ndarray  # (15,) bool
    free_pose: np.ndarray  # (P,) bool
    base_pose: int
    base_point: int
    n_params: int


def layout(n_cams: int, n_poses: int, n_points: int, free_cam: np.ndarray, free_pose: np.ndarray) -> Layout:
    """The :class:`Layout` of ``n_cams`` cameras (``free_cam``: which of :data:`CAM_NAMES` are unknown), poses, corners."""
    n_cam_free = int(free_cam.sum())
    cam_cols = np.full((n_cams, N_CAM), -1)
    cam_cols[:, free_cam] = np.arange(n_cams)[:, None] * n_cam_free + np.arange(n_cam_free)
    base_pose = n_cams * n_cam_free
    base_point = base_pose + 6 * int(free_pose.sum())
    return Layout(cam_cols, free_cam, free_pose, base_pose, base_point, base_point + 3 * n_points)


def rotation_derivatives(rvec: np.ndarray, h: float = 1e-7) -> np.ndarray:
    """Derivatives (..., 3, 3, 3) of :func:`rodrigues` wrt each Rodrigues component j at [..., j] (per rad).

    Central differences on the few rotation matrices (one per camera or pose),
    not on the projections: cheap, and as exact as the analytic form.
    """
    rvec = np.asarray(rvec, dtype=float)
    step = h * np.eye(3)
    return (rodrigues(rvec[..., None, :] + step) - rodrigues(rvec[..., None, :] - step)) / (2 * h)


def jacobian_blocks(pb: Problem, cams, poses, points, free_cam):
    """Per-observation derivative blocks of the projections (analytic chain rule, vectorised).

    Returns ``(Jc, Jp, Jq)``: (N, 2, n_free_cam) wrt the observation's camera's
    free parameters (px per px, per unit distortion term, per rad, per mm),
    (N, 2, 6) wrt its pose (px per rad, per mm) and (N, 2, 3) wrt its corner
    (px per mm, test-field frame), for the model of :func:`project_observations`.
    """
    c = cams[pb.cam]
    Rp = rodrigues(poses[:, :3])[pb.pose]
    Rc = rodrigues(cams[:, 9:12])[pb.cam]
    X = points[pb.point]
    d = np.einsum("nij,nj->ni", Rp, X) + poses[pb.pose, 3:] - c[:, 12:15]  # world point minus centre (mm)
    xc = np.einsum("nij,nj->ni", Rc, d)
    z = xc[:, 2]
    x, y = xc[:, 0] / z, xc[:, 1] / z
    fx, fy = c[:, 0], c[:, 1]
    k1, k2, p1, p2, k3 = c[:, 4], c[:, 5], c[:, 6], c[:, 7], c[:, 8]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    # d(u, v)/d(camera coordinates): focal lengths × distortion × perspective division
    a11, a12, a21, a22 = distort_jacobian(x, y, c[:, 4:9].T)
    dxy = np.zeros((len(z), 2, 3))
    dxy[:, 0, 0] = dxy[:, 1, 1] = 1 / z
    dxy[:, 0, 2], dxy[:, 1, 2] = -x / z, -y / z
    G = np.stack([np.stack([fx * a11, fx * a12], -1), np.stack([fy * a21, fy * a22], -1)], 1) @ dxy  # (N, 2, 3)
    zero, one = np.zeros_like(x), np.ones_like(x)
    iop = np.stack([
        np.stack([xd, zero], -1), np.stack([zero, yd], -1), np.stack([one, zero], -1), np.stack([zero, one], -1),
        np.stack([fx * x * r2, fy * y * r2], -1), np.stack([fx * x * r2 ** 2, fy * y * r2 ** 2], -1),
        np.stack([fx * 2 * x * y, fy * (r2 + 2 * y * y)], -1), np.stack([fx * (r2 + 2 * x * x), fy * 2 * x * y], -1),
        np.stack([fx * x * r2 ** 3, fy * y * r2 ** 3], -1)], axis=2)  # (N, 2, 9)
    GRc = G @ Rc
    dRc = rotation_derivatives(cams[:, 9:12])[pb.cam]  # (N, j, 3, 3)
    d_rot_cam = G @ np.einsum("njab,nb->naj", dRc, d)
    Jc = np.concatenate([iop, d_rot_cam, -GRc], axis=2)[:, :, free_cam]
    dRp = rotation_derivatives(poses[:, :3])[pb.pose]
    d_rot_pose = GRc @ np.einsum("njab,nb->naj", dRp, X)
    Jp = np.concatenate([d_rot_pose, GRc], axis=2)
    Jq = GRc @ Rp
    return Jc, Jp, Jq


def jacobian(pb: Problem, cams, poses, points, lay: Layout) -> sp.csr_matrix:
    """Sparse Jacobian (2N × n_params, rows x0, y0, x1, ...) of the projections wrt the free parameters.

    Every row holds its camera's free parameters, its pose's six (none for
    the datum pose 0) and its corner's three, in increasing column order, so
    the CSR arrays are laid out directly from the per-observation blocks.
    """
    Jc, Jp, Jq = jacobian_blocks(pb, cams, poses, points, lay.free_cam)
    N, nc = len(pb.uv), Jc.shape[2]
    pose_slot = np.cumsum(lay.free_pose) - 1
    cols = np.concatenate([
        lay.cam_cols[pb.cam][:, lay.free_cam],
        lay.base_pose + 6 * pose_slot[pb.pose][:, None] + np.arange(6),
        lay.base_point + 3 * pb.point[:, None] + np.arange(3)], axis=1)  # (N, nc + 9)
    keep = np.ones((N, nc + 9), dtype=bool)
    keep[:, nc:nc + 6] = lay.free_pose[pb.pose][:, None]
    vals = np.concatenate([Jc, Jp, Jq], axis=2)  # (N, 2, nc + 9)
    keep2 = np.broadcast_to(keep[:, None, :], vals.shape)
    indptr = np.concatenate([[0], np.cumsum(keep2.sum(axis=2).ravel())])
    return sp.csr_matrix((vals[keep2], np.broadcast_to(cols[:, None, :], vals.shape)[keep2], indptr),
                         shape=(2 * N, lay.n_params))


@dataclass
class NormalEquations:
    """``N x = b`` split for the Schur complement: N = [[A, B], [Bᵀ, D]].

    A (n_a × n_a) couples the cameras and poses; B (n_a × 3Q) couples them
    with the corners; D (Q, 3, 3) is block diagonal, because an observation
    sees one corner and a corner's survey tie concerns it alone. A and B are
    kept dense: A is small (14 unknowns per camera, 6 per pose: about 300 for
    a 20-camera rig), and B is nearly full, because over the test-field poses
    every camera and every pose sees most corners (a sparse product B D⁻¹ Bᵀ
    was slower than the dense one on the tiny preset).
    """

    A: np.ndarray
    B: np.ndarray
    D: np.ndarray
    b: np.ndarray


def normal_equations(J: sp.csr_matrix, w_obs: np.ndarray, r: np.ndarray, n_a: int, w_pt: float,
                     r_pt: np.ndarray) -> NormalEquations:
    """Weighted normal equations of the observations and the corners' survey ties.

    ``J`` is the sparse Jacobian (:func:`jacobian`), ``w_obs`` the weight of
    each of its rows (1/px²), ``r`` the observations' residuals (px, observed
    − computed), ``r_pt`` the survey minus the current corner coordinates
    (mm, weight ``w_pt`` in 1/mm²). ``n_a`` is the number of camera and pose
    unknowns (the corners' come after them). The full normal matrix is only
    ever formed sparse.
    """
    Jw = sp.csr_matrix(J.multiply(w_obs[:, None]))
    Nmat = (J.T @ Jw).tocsr()
    b = Jw.T @ r
    A = Nmat[:n_a, :n_a].toarray()
    B = Nmat[:n_a, n_a:].toarray()
    Dd = Nmat[n_a:, n_a:].tocoo()
    q = (Nmat.shape[0] - n_a) // 3
    D = np.zeros((q, 3, 3))
    np.add.at(D, (Dd.row // 3, Dd.row % 3, Dd.col % 3), Dd.data)  # rows and columns of one corner: one block
    D[:, np.arange(3), np.arange(3)] += w_pt
    b[n_a:] += w_pt * r_pt
    return NormalEquations(A, B, D, b)


def _reduce(ne: NormalEquations, lam: float):
    """Damped Schur complement on the cameras and poses: ``(S, B D⁻¹, D⁻¹)``.

    Levenberg–Marquardt damping scales the diagonal: ``N + lam diag(N)``.
    """
    A, D = ne.A, ne.D
    if lam:
        A = A + lam * np.diag(np.maximum(np.diag(A), 1e-12))
        D = D.copy()
        i3 = np.arange(3)
        D[:, i3, i3] += lam * np.maximum(D[:, i3, i3], 1e-12)
    Dinv = np.linalg.inv(D)
    n_a, q = len(A), len(D)
    BD = np.einsum("aqi,qij->aqj", ne.B.reshape(n_a, q, 3), Dinv).reshape(n_a, 3 * q)
    return A - BD @ ne.B.T, BD, Dinv


def solve_normal(ne: NormalEquations, lam: float) -> np.ndarray:
    """The damped step: corners eliminated first (3×3 blocks), the reduced camera/pose system solved dense.

    Raises ``numpy.linalg.LinAlgError`` when the system is singular.
    """
    S, BD, Dinv = _reduce(ne, lam)
    n_a = len(S)
    xa = np.linalg.solve(S, ne.b[:n_a] - BD @ ne.b[n_a:])
    xd = np.einsum("qij,qj->qi", Dinv, (ne.b[n_a:] - ne.B.T @ xa).reshape(-1, 3)).ravel()
    return np.concatenate([xa, xd])


def inverse_normal(ne: NormalEquations):
    """Cofactor matrix of the cameras and poses (n_a × n_a), and the diagonal of the corners' part (3Q,)."""
    S, BD, Dinv = _reduce(ne, 0.0)
    try:
        Qa = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        Qa = np.linalg.pinv(S)
    # diag of Q_dd = D⁻¹ + (D⁻¹Bᵀ) Qa (B D⁻¹)
    extra = np.einsum("ak,ak->k", Qa @ BD, BD)
    return Qa, np.einsum("qii->qi", Dinv).ravel() + extra


def _cost(pb, w_obs, w_pt, survey, cams, poses, points):
    r = (pb.uv - project_observations(cams, poses, points, pb.cam, pb.pose, pb.point)).ravel()
    r_pt = (survey - points).ravel()
    return r, r_pt, float(r @ (w_obs * r) + w_pt * r_pt @ r_pt)


ROUND_TOL = 1e-7  # relative change of the cost that ends a round followed by a rejection of blunders
FINAL_TOL = 1e-10  # ... and the last round


def _standardized(pb, inlier, cams, poses, points, survey, lay):
    """A posteriori sigma0, residuals (px), projections and each corner's standardized residual."""
    pred = project_observations(cams, poses, points, pb.cam, pb.pose, pb.point)
    res = pb.uv - pred
    dof = 2 * inlier.sum() - (lay.n_params - points.size)  # target pseudo-observations balance their unknowns
    sigma0 = np.sqrt(max((np.sum(pb.weight[inlier, None] * res[inlier] ** 2) / pb.sigma_px ** 2
                          + np.sum((survey - points) ** 2) / pb.sigma_mm ** 2) / max(dof, 1), 1e-12))
    std_res = np.linalg.norm(res, axis=1) * np.sqrt(pb.weight) / (pb.sigma_px * sigma0 * np.sqrt(2))
    return sigma0, res, pred, std_res


def adjust(pb: Problem, max_iterations: int = 30, reject_k: float = 4.0, robust_rounds: int = 4,
           correlation_warn: float = 0.95, max_damping_tries: int = 12) -> Solution:
    """Solve the bundle adjustment; see the module docstring.

    Parameters
    ----------
    reject_k : float
        Observations whose standardized residual exceeds ``reject_k`` are
        removed (one corner at a time: the x and y of a corner go together),
        then the adjustment is repeated, ``robust_rounds`` times at most.
    max_damping_tries : int
        Levenberg–Marquardt: damped steps tried per iteration (λ × 10 each)
        before the iteration gives up; 12 span λ over 12 decades, from the
        smallest it reaches (1e-9) to steepest descent.

    ``Solution.converged`` and ``Solution.reason`` tell how the last round ended:
    the cost or the step fell below tolerance (converged), or the iteration
    limit, a singular system or no damping that lowers the cost (not converged;
    the best parameters reached are returned).
    """
    cams, poses, points = pb.cams.astype(float).copy(), pb.poses.astype(float).copy(), pb.points.astype(float).copy()
    survey = pb.points.astype(float)
    free_cam = np.array([n not in pb.fixed_iop for n in CAM_NAMES])
    free_pose = np.arange(len(poses)) > 0
    lay = layout(len(cams), len(poses), len(points), free_cam, free_pose)
    w_pt = 1.0 / pb.sigma_mm ** 2
    inlier = np.ones(len(pb.uv), dtype=bool)
    history = []
    it_total = 0
    lam = 1e-3

    def iterate(w_obs, rel_tol, round_):
        """Levenberg–Marquardt iterations until the cost changes by less than ``rel_tol`` of itself."""
        nonlocal cams, poses, points, lam, it_total
        lam = min(lam, 1e-3)  # a round goes on from the last round's damping, never from a gave-up one
        for it in range(max_iterations):
            it_total += 1
            r, r_pt, cost = _cost(pb, w_obs, w_pt, survey, cams, poses, points)
            J = jacobian(pb, cams, poses, points, lay)
            ne = normal_equations(J, w_obs, r, lay.base_point, w_pt, r_pt)
            accepted, best_rise, singular = False, np.inf, 0
            for _ in range(max_damping_tries):
                try:
                    dx = solve_normal(ne, lam)
                except np.linalg.LinAlgError:
                    dx = None
                if dx is None or not np.all(np.isfinite(dx)):
                    singular += 1
                    lam *= 10
                    continue
                new = _apply(dx, cams, poses, points, lay)
                _, _, cost_new = _cost(pb, w_obs, w_pt, survey, *new)
                if cost_new <= cost:
                    accepted = True
                    break
                best_rise = min(best_rise, cost_new - cost)
                lam *= 10
            tol = rel_tol * max(cost, 1.0)
            if not accepted:
                history.append({"round": round_, "cost": cost})
                if best_rise < tol:
                    # every damped step changed the cost by less than the tolerance: at the minimum
                    return True, "at the minimum: no step changes the cost beyond tolerance"
                if singular == max_damping_tries:
                    return False, f"singular or non-finite normal equations in all {max_damping_tries} damping tries"
                return False, (f"no step lowered the cost in {max_damping_tries} damping tries "
                               f"(lambda up to {lam / 10:.0e})")
            cams, poses, points = new
            lam = max(lam / 10, 1e-9)
            history.append({"round": round_, "cost": cost_new})
            step_px = np.abs(dx[:lay.base_pose]).max() if lay.base_pose else 0.0
            if cost - cost_new < tol:
                return True, "cost change below tolerance"
            if step_px < 1e-7 and np.abs(dx).max() < 1e-6:
                return True, "step below tolerance"
        return False, f"iteration limit ({max_iterations}) reached"

    for round_ in range(robust_rounds + 1):
        w_obs = np.repeat(pb.weight * inlier, 2) / pb.sigma_px ** 2
        # a round that rejects blunders after it only has to find them: it stops at a looser tolerance; the
        # last round goes on to the tight one (paper-scale calibration, seed 32: 68 -> 29 iterations, the
        # same costs and rejections)
        converged, reason = iterate(w_obs, ROUND_TOL if round_ < robust_rounds else FINAL_TOL, round_)
        sigma0, res, pred, std_res = _standardized(pb, inlier, cams, poses, points, survey, lay)
        bad = inlier & (std_res > reject_k)
        if not bad.any() or round_ == robust_rounds:
            if converged and round_ < robust_rounds:
                converged, reason = iterate(w_obs, FINAL_TOL, round_)
                sigma0, res, pred, std_res = _standardized(pb, inlier, cams, poses, points, survey, lay)
            break
        # remove the worst ones first: a blunder inflates its neighbours' residuals
        worst = std_res[bad].max()
        inlier &= ~(bad & (std_res > max(reject_k, 0.5 * worst)))

    # precision from the normal matrix at the solution
    w_obs = np.repeat(pb.weight * inlier, 2) / pb.sigma_px ** 2
    J = jacobian(pb, cams, poses, points, lay)
    ne = normal_equations(J, w_obs, np.zeros(J.shape[0]), lay.base_point, w_pt, np.zeros(points.size))
    Q, point_diag = inverse_normal(ne)
    cov_scale = sigma0 ** 2
    sd = np.sqrt(np.clip(np.concatenate([np.diag(Q), point_diag]), 0, None) * cov_scale)
    cam_cols = lay.cam_cols
    cam_sigma = np.zeros_like(cams)
    valid = cam_cols >= 0
    cam_sigma[valid] = sd[cam_cols[valid]]
    # joint covariance of every camera's parameters: cameras share the test field's poses and
    # points, so their errors correlate (what a comparison of cameras of one arm propagates)
    flat_cols = cam_cols.ravel()
    flat_ok = np.flatnonzero(flat_cols >= 0)
    cams_cov = np.zeros((flat_cols.size, flat_cols.size))
    cams_cov[np.ix_(flat_ok, flat_ok)] = Q[np.ix_(flat_cols[flat_ok], flat_cols[flat_ok])] * cov_scale
    cam_cov = np.stack([cams_cov[c * N_CAM:(c + 1) * N_CAM, c * N_CAM:(c + 1) * N_CAM] for c in range(len(cams))])
    pose_sigma = np.zeros_like(poses)
    k = np.flatnonzero(free_pose)
    pose_sigma[k] = sd[lay.base_pose: lay.base_point].reshape(-1, 6)
    point_sigma = sd[lay.base_point:].reshape(-1, 3)
    correlations = []
    iop = np.array([n in IOP_NAMES for n in CAM_NAMES])
    for c in range(len(cams)):
        ids = cam_cols[c][valid[c]]
        names = [n for n, v in zip(CAM_NAMES, valid[c]) if v]
        sub = Q[np.ix_(ids, ids)]
        d = np.sqrt(np.diag(sub))
        rho = sub / np.outer(d, d)
        is_iop = iop[valid[c]]
        a_idx, b_idx = np.triu_indices(len(ids), 1)
        hit = (is_iop[a_idx] != is_iop[b_idx]) & (np.abs(rho[a_idx, b_idx]) > correlation_warn)
        correlations += [(c, names[a], names[b], float(rho[a, b])) for a, b in zip(a_idx[hit], b_idx[hit])]
    return Solution(cams, poses, points, pb.uv - pred, inlier, float(sigma0), cam_sigma, pose_sigma, point_sigma,
                    correlations, it_total, converged, history, cam_cov, cams_cov, reason)


def _apply(dx, cams, poses, points, lay: Layout):
    """Parameters after the step ``dx`` (new arrays)."""
    cams = cams.copy()
    valid = lay.cam_cols >= 0
    cams[valid] += dx[lay.cam_cols[valid]]
    poses = poses.copy()
    k = np.flatnonzero(lay.free_pose)
    if len(k):
        poses[k] += dx[lay.base_pose: lay.base_point].reshape(-1, 6)
    points = points + dx[lay.base_point:].reshape(-1, 3)
    return cams, poses, points
