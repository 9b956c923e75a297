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
point) and is formed by central differences over each parameter block at
once. Blunders are removed by iterated rejection of standardized residuals;
precision comes from the inverse of the normal matrix scaled by the a
posteriori variance factor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

IOP_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
EOP_NAMES = ("rx", "ry", "rz", "X", "Y", "Z")
CAM_NAMES = IOP_NAMES + EOP_NAMES
N_CAM = len(CAM_NAMES)
POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")

# central-difference steps per parameter (px, unitless, rad, mm)
_CAM_STEP = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6, 1e-7, 1e-7, 1e-7, 1e-3, 1e-3, 1e-3])
_POSE_STEP = np.array([1e-7, 1e-7, 1e-7, 1e-3, 1e-3, 1e-3])
_POINT_STEP = 1e-3


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


def _jacobian(pb: Problem, cams, poses, points, free_cam, free_pose):
    """Sparse Jacobian of the projections wrt the free parameters (central differences)."""
    N = len(pb.uv)
    n_cam_free = int(free_cam.sum())
    C = len(cams)
    rows, cols, vals = [], [], []
    obs_rows = np.arange(N)
    col = 0
    cam_cols = np.full((C, N_CAM), -1)
    for j in range(N_CAM):
        if not free_cam[j]:
            continue
        cam_cols[:, j] = col + np.arange(C) * n_cam_free
        col += 1
    n_cam_total = C * n_cam_free
    for j in range(N_CAM):
        if not free_cam[j]:
            continue
        h = _CAM_STEP[j]
        plus, minus = cams.copy(), cams.copy()
        plus[:, j] += h
        minus[:, j] -= h
        d = (project_observations(plus, poses, points, pb.cam, pb.pose, pb.point)
             - project_observations(minus, poses, points, pb.cam, pb.pose, pb.point)) / (2 * h)
        for a in (0, 1):
            rows.append(2 * obs_rows + a)
            cols.append(cam_cols[pb.cam, j])
            vals.append(d[:, a])
    n_pose_free = int(free_pose.sum())  # poses 1.. are free
    base_pose = n_cam_total
    for j in range(6):
        h = _POSE_STEP[j]
        plus, minus = poses.copy(), poses.copy()
        plus[:, j] += h
        minus[:, j] -= h
        d = (project_observations(cams, plus, points, pb.cam, pb.pose, pb.point)
             - project_observations(cams, minus, points, pb.cam, pb.pose, pb.point)) / (2 * h)
        sel = free_pose[pb.pose]
        pose_col = base_pose + (np.cumsum(free_pose) - 1)[pb.pose[sel]] * 6 + j
        for a in (0, 1):
            rows.append(2 * obs_rows[sel] + a)
            cols.append(pose_col)
            vals.append(d[sel, a])
    base_point = base_pose + n_pose_free * 6
    for j in range(3):
        h = _POINT_STEP
        plus, minus = points.copy(), points.copy()
        plus[:, j] += h
        minus[:, j] -= h
        d = (project_observations(cams, poses, plus, pb.cam, pb.pose, pb.point)
             - project_observations(cams, poses, minus, pb.cam, pb.pose, pb.point)) / (2 * h)
        for a in (0, 1):
            rows.append(2 * obs_rows + a)
            cols.append(base_point + pb.point * 3 + j)
            vals.append(d[:, a])
    n_params = base_point + len(points) * 3
    J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(2 * N, n_params))
    return J, cam_cols, base_pose, base_point, n_params


def adjust(pb: Problem, max_iterations: int = 30, reject_k: float = 4.0, robust_rounds: int = 4,
           correlation_warn: float = 0.95) -> Solution:
    """Solve the bundle adjustment; see the module docstring.

    Parameters
    ----------
    reject_k : float
        Observations whose standardized residual exceeds ``reject_k`` are
        removed (one corner at a time: the x and y of a corner go together),
        then the adjustment is repeated, ``robust_rounds`` times at most.
    """
    cams, poses, points = pb.cams.astype(float).copy(), pb.poses.astype(float).copy(), pb.points.astype(float).copy()
    survey = pb.points.astype(float)
    free_cam = np.array([n not in pb.fixed_iop for n in CAM_NAMES])
    free_pose = np.arange(len(poses)) > 0
    inlier = np.ones(len(pb.uv), dtype=bool)
    history = []
    it_total = 0
    converged = False
    for round_ in range(robust_rounds + 1):
        w_obs = np.repeat(pb.weight * inlier, 2) / pb.sigma_px ** 2
        lam = 1e-3
        for it in range(max_iterations):
            it_total += 1
            pred = project_observations(cams, poses, points, pb.cam, pb.pose, pb.point)
            r = (pb.uv - pred).ravel()
            J, cam_cols, base_pose, base_point, n_params = _jacobian(pb, cams, poses, points, free_cam, free_pose)
            r_pt = (survey - points).ravel()
            w_pt = 1.0 / pb.sigma_mm ** 2
            JW = J.T.multiply(w_obs).tocsr()
            Nmat = (JW @ J).toarray()
            b = JW @ r
            idx_pt = base_point + np.arange(points.size)
            Nmat[idx_pt, idx_pt] += w_pt
            b[idx_pt] += w_pt * r_pt
            cost = float(r @ (w_obs * r) + w_pt * r_pt @ r_pt)
            # Levenberg–Marquardt: damp the diagonal, accept steps that lower the cost
            diag = np.diag(Nmat).copy()
            while True:
                try:
                    dx = _solve_schur(Nmat + lam * np.diag(np.maximum(diag, 1e-12)), b, base_point)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                new_cams, new_poses, new_points = _apply(dx, cams, poses, points, cam_cols, free_pose, base_pose, base_point)
                pred_new = project_observations(new_cams, new_poses, new_points, pb.cam, pb.pose, pb.point)
                r_new = (pb.uv - pred_new).ravel()
                r_pt_new = (survey - new_points).ravel()
                cost_new = float(r_new @ (w_obs * r_new) + w_pt * r_pt_new @ r_pt_new)
                if cost_new <= cost or lam > 1e8:
                    break
                lam *= 10
            if cost_new <= cost:
                cams, poses, points = new_cams, new_poses, new_points
                lam = max(lam / 10, 1e-9)
            history.append({"round": round_, "cost": cost_new})
            step_px = np.abs(dx[:base_pose]).max() if base_pose else 0.0
            if cost - cost_new < 1e-10 * max(cost, 1.0) or (step_px < 1e-7 and np.abs(dx).max() < 1e-6):
                converged = True
                break
        # a posteriori variance factor and rejection of blunders
        pred = project_observations(cams, poses, points, pb.cam, pb.pose, pb.point)
        res = pb.uv - pred
        dof = 2 * inlier.sum() - (n_params - points.size)  # target pseudo-observations balance their unknowns
        sigma0 = np.sqrt(max((np.sum(pb.weight[inlier, None] * res[inlier] ** 2) / pb.sigma_px ** 2
                              + np.sum((survey - points) ** 2) / pb.sigma_mm ** 2) / max(dof, 1), 1e-12))
        std_res = np.linalg.norm(res, axis=1) * np.sqrt(pb.weight) / (pb.sigma_px * sigma0 * np.sqrt(2))
        bad = inlier & (std_res > reject_k)
        if not bad.any() or round_ == robust_rounds:
            break
        # remove the worst ones first: a blunder inflates its neighbours' residuals
        worst = std_res[bad].max()
        inlier &= ~(bad & (std_res > max(reject_k, 0.5 * worst)))

    # precision from the normal matrix at the solution
    J, cam_cols, base_pose, base_point, n_params = _jacobian(pb, cams, poses, points, free_cam, free_pose)
    w_obs = np.repeat(pb.weight * inlier, 2) / pb.sigma_px ** 2
    Nmat = (J.T.multiply(w_obs).tocsr() @ J).toarray()
    idx_pt = base_point + np.arange(points.size)
    Nmat[idx_pt, idx_pt] += 1.0 / pb.sigma_mm ** 2
    Q, point_diag = _inverse_schur(Nmat, base_point)
    cov_scale = sigma0 ** 2
    sd = np.sqrt(np.clip(np.concatenate([np.diag(Q), point_diag]), 0, None) * cov_scale)
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
    for i, p in enumerate(k):
        pose_sigma[p] = sd[base_pose + 6 * i: base_pose + 6 * i + 6]
    point_sigma = sd[base_point:].reshape(-1, 3)
    correlations = []
    for c in range(len(cams)):
        ids = cam_cols[c][valid[c]]
        names = [n for n, v in zip(CAM_NAMES, valid[c]) if v]
        sub = Q[np.ix_(ids, ids)]
        d = np.sqrt(np.diag(sub))
        rho = sub / np.outer(d, d)
        for a in range(len(ids)):
            for b in range(a + 1, len(ids)):
                iop_eop = (names[a] in IOP_NAMES) != (names[b] in IOP_NAMES)
                if iop_eop and abs(rho[a, b]) > correlation_warn:
                    correlations.append((c, names[a], names[b], float(rho[a, b])))
    return Solution(cams, poses, points, pb.uv - pred, inlier, float(sigma0), cam_sigma, pose_sigma, point_sigma,
                    correlations, it_total, converged, history, cam_cov, cams_cov)


def _apply(dx, cams, poses, points, cam_cols, free_pose, base_pose, base_point):
    cams = cams.copy()
    valid = cam_cols >= 0
    cams[valid] += dx[cam_cols[valid]]
    poses = poses.copy()
    k = np.flatnonzero(free_pose)
    if len(k):
        poses[k] += dx[base_pose: base_pose + 6 * len(k)].reshape(-1, 6)
    points = points + dx[base_point:].reshape(-1, 3)
    return cams, poses, points


def _blocks(Nmat, n_a):
    """Split the normal matrix: camera/pose block A, coupling B, 3x3 point blocks D."""
    A = Nmat[:n_a, :n_a]
    B = Nmat[:n_a, n_a:]
    q = (Nmat.shape[0] - n_a) // 3
    idx = n_a + 3 * np.arange(q)[:, None] + np.arange(3)
    D = Nmat[idx[:, :, None], idx[:, None, :]]  # (q, 3, 3)
    return A, B, D, q


def _solve_schur(Nmat, b, n_a):
    """Solve the normal equations by eliminating the points (3x3 blocks) first."""
    A, B, D, q = _blocks(Nmat, n_a)
    Dinv = np.linalg.inv(D)
    BD = np.einsum("aqi,qij->aqj", B.reshape(n_a, q, 3), Dinv).reshape(n_a, 3 * q)
    S = A - BD @ B.T
    rhs = b[:n_a] - BD @ b[n_a:]
    xa = np.linalg.solve(S, rhs)
    xd = np.einsum("qij,qj->qi", Dinv, (b[n_a:] - B.T @ xa).reshape(q, 3)).ravel()
    return np.concatenate([xa, xd])


def _inverse_schur(Nmat, n_a):
    """Cofactor matrix of the cameras and poses, and the diagonal of the points' part."""
    A, B, D, q = _blocks(Nmat, n_a)
    Dinv = np.linalg.inv(D)
    BD = np.einsum("aqi,qij->aqj", B.reshape(n_a, q, 3), Dinv).reshape(n_a, 3 * q)
    S = A - BD @ B.T
    try:
        Qa = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        Qa = np.linalg.pinv(S)
    # diag of Q_dd = D^-1 + (D^-1 B^T) Qa (B D^-1)
    extra = np.einsum("ak,ab,bk->k", BD, Qa, BD)
    point_diag = np.einsum("qii->qi", Dinv).ravel() + extra
    return Qa, point_diag
