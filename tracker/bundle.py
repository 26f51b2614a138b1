"""Bundle adjustment in NumPy: Levenberg-Marquardt on the Schur complement, vectorised over observations.

An RGB-D observation is modelled the way ORB-SLAM does: as a rectified stereo measurement
(u_left, u_right = u_left - bf / z, v), where the virtual baseline `bf` is chosen so that one pixel on
u_right equals the tracker's inverse-depth sigma. A keypoint without depth is a plain (u, v)
projection. Every observation has a Huber kernel at the chi-square 95% threshold and sigma =
scale_factor ** octave pixels. As in ORB-SLAM, the optimisation runs twice: after the first run the
observations that fail the chi-square test are dropped, then it runs again without them.

Why not gtsam, which the pose graph uses: a local BA is ~10 keyframes, 800 points and 3,000
observations, and building 3,000 gtsam factors one Python call at a time cost more than solving them
(100 ms per keyframe on a 2-core EPYC, 90% of it outside the solver). Here each iteration is a
handful of array operations over all observations: residuals and Jacobians at once, the point blocks
eliminated in closed form (3x3 each), and the reduced camera system (6 per free keyframe) solved
dense. Fixed keyframes are constants, not priors. Sums run in a fixed order (sorted segments, never
threads), so equal input gives equal bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from octolog.tracker.pose import CHI2_2DOF, CHI2_3DOF, so3_exp

# Levenberg-Marquardt damping: start, factor per rejected / accepted step, and the give-up bound
LAMBDA_START = 1e-5
LAMBDA_FACTOR = 10.0
LAMBDA_MAX = 1e5
# stop once an accepted step lowers the cost by less than this fraction
RELATIVE_DECREASE = 1e-5
# squared whitened error charged for a point behind its camera (a gross outlier, never a free pass)
BEHIND_CHI2 = 1e6
# the reduced system is built from dense camera x point matrices up to this many (camera, point) cells
DENSE_MAX_CELLS = 40_000


@dataclass(frozen=True)
class BundleProblem:
    """Keyframes, points and observations of a bundle adjustment (indices are local)."""

    poses_wc: np.ndarray  # (K, 4, 4) world_from_camera
    fixed: np.ndarray  # (K,) bool: held constant (the window's covisible neighbours, the origin)
    points: np.ndarray  # (P, 3) world positions
    obs_kf: np.ndarray  # (M,) index into poses_wc
    obs_pt: np.ndarray  # (M,) index into points
    obs_uv: np.ndarray  # (M, 2) undistorted pixels
    obs_z: np.ndarray  # (M,) depth in metres, 0 when none
    obs_sigma: np.ndarray  # (M,) pixel sigma (scale_factor ** octave)
    K: tuple[float, float, float, float]  # fx, fy, cx, cy
    bf: float  # virtual stereo baseline times fx, in pixel metres
    # the gyro's rotations between keyframes (tracker/inertial.py: Inertial.keyframe_rotation): local
    # indices (a, b), camera_a_from_camera_b rotation, and its sigma in rad
    rot_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    rot_ab: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    rot_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class BundleResult:
    poses_wc: np.ndarray  # (K, 4, 4)
    points: np.ndarray  # (P, 3)
    inliers: np.ndarray  # (M,) bool: observations that pass the chi-square test at the end
    iterations: int
    error_before: float
    error_after: float


def _residual(problem: BundleProblem, p: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residuals (n, 3; the third is 0 without depth) of observations `m` whose points are
    at `p` in their cameras' frames, and whether each point is in front of its camera."""
    fx, fy, cx, cy = problem.K
    z = p[:, 2]
    front = z > 1e-6
    iz = 1.0 / np.where(front, z, 1e-6)
    u = fx * p[:, 0] * iz + cx
    v = fy * p[:, 1] * iz + cy
    obs_z = problem.obs_z[m]
    has_d = obs_z > 0
    ur_meas = problem.obs_uv[m, 0] - problem.bf / np.where(has_d, obs_z, 1.0)
    e = np.stack([u - problem.obs_uv[m, 0], v - problem.obs_uv[m, 1],
                  np.where(has_d, u - problem.bf * iz - ur_meas, 0.0)], axis=1)
    return e / problem.obs_sigma[m, None], front


def observation_chi2(problem: BundleProblem, poses_wc: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Squared whitened residual of every observation (stereo where there is depth, else mono)."""
    p = _tv(poses_wc[problem.obs_kf, :3, :3], points[problem.obs_pt] - poses_wc[problem.obs_kf, :3, 3])
    e, front = _residual(problem, p, np.arange(problem.obs_kf.size))
    return np.where(front, (e * e).sum(axis=1), np.inf)


def _huber(chi2: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cost and IRLS weight of each whitened residual of squared norm chi2, Huber threshold k."""
    e = np.sqrt(chi2)
    inside = e <= k
    cost = np.where(inside, 0.5 * chi2, k * e - 0.5 * k * k)
    return cost, np.where(inside, 1.0, k / np.maximum(e, 1e-300))


def _segment_sum(values: np.ndarray, order: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Sums of `values` rows over segments: rows `order[starts[i]:starts[i+1]]` make segment i."""
    return np.add.reduceat(values[order], starts, axis=0)


def _segments(index: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, starts) grouping rows by `index`, one segment per entry of the sorted `values`
    (each present in `index`), rows in a stable order."""
    order = np.argsort(index, kind="stable")
    return order, np.searchsorted(index[order], values)


# Batched products of small matrices, (n, ...) each: the fastest NumPy form for each shape, measured
# on 3x3 to 6x6 blocks (np.matmul on contiguous operands; np.einsum only for matrix-vector products).
def _tv(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """a^T x"""
    return np.einsum("nki,nk->ni", a, x)


def _mv(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """a x"""
    return np.einsum("nij,nj->ni", a, x)


def _t(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.swapaxes(a, 1, 2))


def _tn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^T b"""
    return np.matmul(_t(a), b)


def _nn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a b"""
    return np.matmul(a, b)


def _nt(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a b^T"""
    return np.matmul(a, _t(b))


def _inverse_cholesky3(M: np.ndarray) -> np.ndarray:
    """D = C^-1 for the Cholesky factors C C^T = M of (n, 3, 3) symmetric positive definite matrices,
    in closed form (np.linalg calls LAPACK once per matrix), so that M^-1 = D^T D. Raises
    LinAlgError when one is not positive definite."""
    a00, a10, a11 = M[:, 0, 0], M[:, 1, 0], M[:, 1, 1]
    a20, a21, a22 = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        c00 = np.sqrt(a00)
        c10, c20 = a10 / c00, a20 / c00
        c11 = np.sqrt(a11 - c10 * c10)
        c21 = (a21 - c20 * c10) / c11
        c22 = np.sqrt(a22 - c20 * c20 - c21 * c21)
        D = np.zeros_like(M)
        D[:, 0, 0], D[:, 1, 1], D[:, 2, 2] = 1.0 / c00, 1.0 / c11, 1.0 / c22
        D[:, 1, 0] = -c10 * D[:, 0, 0] / c11
        D[:, 2, 1] = -c21 * D[:, 1, 1] / c22
        D[:, 2, 0] = -(c20 * D[:, 0, 0] + c21 * D[:, 1, 0]) / c22
    if not np.all(np.isfinite(D)) or not np.all(c22 > 0):
        raise np.linalg.LinAlgError("a point's block is not positive definite")
    return D


def _skew(p: np.ndarray) -> np.ndarray:
    S = np.zeros(p.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -p[..., 2], p[..., 1]
    S[..., 1, 0], S[..., 1, 2] = p[..., 2], -p[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -p[..., 1], p[..., 0]
    return S


def _log_batch(E: np.ndarray) -> np.ndarray:
    """Rotation vectors of (n, 3, 3) rotations (angles below pi)."""
    w = 0.5 * np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], axis=1)
    s = np.linalg.norm(w, axis=1)
    theta = np.arctan2(s, 0.5 * (np.trace(E, axis1=1, axis2=2) - 1.0))
    return w * np.where(s > 1e-12, theta / np.maximum(s, 1e-300), 1.0)[:, None]


class _GyroFactors:
    """The gyro's rotations between keyframes as residuals r = log(dR^T R_a^T R_b) / sigma (Huber at
    the 3-dof chi-square bound), on the pairs with a free keyframe; each free keyframe's rotation
    perturbed on the right as the observations' are."""

    def __init__(self, problem: BundleProblem, cam: np.ndarray) -> None:
        pairs = problem.rot_pairs
        keep = (cam[pairs[:, 0]] >= 0) | (cam[pairs[:, 1]] >= 0) if pairs.size else np.zeros(0, bool)
        self.a, self.b = pairs[keep, 0], pairs[keep, 1]
        self.ca, self.cb = cam[self.a], cam[self.b]  # free-camera index, -1 on a fixed one
        self.meas_t = _t(problem.rot_ab[keep])
        self.inv_sigma = 1.0 / problem.rot_sigma[keep]
        self.k = np.sqrt(CHI2_3DOF)

    def residuals(self, poses: np.ndarray) -> tuple[float, tuple]:
        Ra, Rb = poses[self.a, :3, :3], poses[self.b, :3, :3]
        r = _log_batch(_nn(self.meas_t, _tn(Ra, Rb))) * self.inv_sigma[:, None]
        cost, w = _huber((r * r).sum(axis=1), self.k)
        return float(cost.sum()), (Ra, Rb, r, w)

    def add_to(self, state: tuple, U: np.ndarray, gc: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
        """Adds the factors' blocks to the free cameras' U and gc; returns the cross blocks (ca, cb, 6x6)."""
        Ra, Rb, r, w = state
        sw = np.sqrt(w)[:, None, None] * self.inv_sigma[:, None, None]
        Jb = (np.eye(3) + 0.5 * _skew(r / self.inv_sigma[:, None])) * sw  # right Jacobian inverse, first order
        Ja = -_nn(Jb, _tn(Rb, Ra))
        e = r * np.sqrt(w)[:, None]
        cross = []
        for n in range(self.a.size):
            ca, cb = int(self.ca[n]), int(self.cb[n])
            for c, J in ((ca, Ja[n]), (cb, Jb[n])):
                if c >= 0:
                    U[c, :3, :3] += J.T @ J
                    gc[c, :3] += J.T @ e[n]
            if ca >= 0 and cb >= 0:
                block = np.zeros((6, 6))
                block[:3, :3] = Ja[n].T @ Jb[n]
                cross.append((ca, cb, block))
        return cross


class _Solve:
    """One Levenberg-Marquardt run over the observations `ms` of a problem."""

    def __init__(self, problem: BundleProblem, ms: np.ndarray) -> None:
        self.problem = problem
        self.ms = ms
        obs_kf, obs_pt = problem.obs_kf[ms], problem.obs_pt[ms]
        self.obs_kf, self.obs_pt = obs_kf, obs_pt
        kfs = np.unique(obs_kf)
        self.free = kfs[~problem.fixed[kfs]]
        self.pts = np.unique(obs_pt)
        cam = np.full(len(problem.poses_wc), -1)
        cam[self.free] = np.arange(self.free.size)
        self.cam = cam[obs_kf]  # free-camera index of each observation, -1 on a fixed camera
        self.gyro = _GyroFactors(problem, cam)
        self.pt = np.searchsorted(self.pts, obs_pt)  # point index of each observation
        self.k = np.sqrt(np.where(problem.obs_z[ms] > 0, CHI2_3DOF, CHI2_2DOF))
        self.has_d = problem.obs_z[ms] > 0
        self.sigma = problem.obs_sigma[ms]
        # every observation by point; the free cameras' observations by camera, and by point
        self.pt_order, self.pt_starts = _segments(self.pt, np.arange(self.pts.size))
        on_free = np.flatnonzero(self.cam >= 0)
        self.fm = on_free[np.argsort(self.cam[on_free], kind="stable")]
        _, self.fm_cam_starts = _segments(self.cam[self.fm], np.arange(self.free.size))
        self.fm_pts = np.unique(self.pt[self.fm])
        self.fm_pt_order, self.fm_pt_starts = _segments(self.pt[self.fm], self.fm_pts)
        # the reduced system from a dense camera-by-point matrix (one product) when it is small, as in a
        # local BA, else from a sparse one (a final BA over hundreds of keyframes)
        cell = self.cam[self.fm] * self.pts.size + self.pt[self.fm]
        self.dense = self.free.size * self.pts.size <= DENSE_MAX_CELLS and np.unique(cell).size == cell.size
        if not self.dense:
            self._sparse()

    def _sparse(self) -> None:
        """The layout of G (6 rows per free camera, 3 columns per point) as a CSR matrix, so that
        the reduced system's G G^T is one sparse product. The free observations are ordered by
        (camera, point) once: a camera that sees a point twice gives one 6x3 block, the sum of its
        observations' blocks in observation order; each camera's 6 rows then list its blocks'
        columns in point order. Index arrays per block, not per entry: a final BA over hundreds of
        keyframes holds 18 times fewer of them (an argsort over every entry once cost the worker
        ~90 MB at 258 keyframes)."""
        npts, nf = self.pts.size, self.free.size
        key = self.cam[self.fm] * npts + self.pt[self.fm]
        self.blk_order = np.argsort(key, kind="stable")  # into `fm` order
        key = key[self.blk_order]
        self.blk_starts = np.flatnonzero(np.r_[np.ones(min(1, key.size), bool), key[1:] != key[:-1]])
        key = key[self.blk_starts]
        self.cam_blocks = np.searchsorted(key // npts, np.arange(nf + 1))  # each camera's blocks
        counts = np.diff(self.cam_blocks)
        self.csr_indptr = np.r_[0, np.cumsum(np.repeat(3 * counts, 6))].astype(np.int32)
        cols = (3 * (key % npts))[:, None] + np.arange(3)  # (blocks, 3)
        self.csr_indices = np.concatenate(
            [np.tile(cols[s:e].reshape(-1), 6) for s, e in zip(self.cam_blocks[:-1], self.cam_blocks[1:])]
            or [np.zeros(0, np.int64)]).astype(np.int32)

    def _csr_data(self, G: np.ndarray) -> np.ndarray:
        """G's values (free observations, 6, 3) in the CSR order of `_sparse`."""
        blocks = np.add.reduceat(G[self.blk_order], self.blk_starts, axis=0) if G.shape[0] else G
        return np.concatenate([blocks[s:e].transpose(1, 0, 2).reshape(-1)
                               for s, e in zip(self.cam_blocks[:-1], self.cam_blocks[1:])] or [np.zeros(0)])

    def residuals(self, poses: np.ndarray, X: np.ndarray) -> tuple:
        """(cost, what `normal_equations` needs) at poses, X."""
        RT = _t(poses[:, :3, :3])[self.obs_kf]  # camera_from_world rotation of each observation
        p = _mv(RT, X[self.obs_pt] - poses[self.obs_kf, :3, 3])
        e, front = _residual(self.problem, p, self.ms)
        # a point behind its camera counts as a gross outlier: a step that puts it there costs
        chi2 = np.where(front, (e * e).sum(axis=1), BEHIND_CHI2)
        cost, w = _huber(chi2, self.k)
        gyro_cost, gyro_state = self.gyro.residuals(poses)
        return float(cost.sum()) + gyro_cost, (RT, p, e, np.where(front, w, 0.0), gyro_state)

    def normal_equations(self, state: tuple):
        fx, fy = self.problem.K[0], self.problem.K[1]
        RT, p, e, w, gyro_state = state
        iz = 1.0 / np.where(w > 0, p[:, 2], 1.0)
        d = self.has_d.astype(np.float64)
        A = np.zeros((p.shape[0], 3, 3))  # d(u, v, u_right) / d(camera-frame point)
        A[:, 0, 0] = fx * iz
        A[:, 0, 2] = -fx * p[:, 0] * iz * iz
        A[:, 1, 1] = fy * iz
        A[:, 1, 2] = -fy * p[:, 1] * iz * iz
        A[:, 2, 0] = d * A[:, 0, 0]
        A[:, 2, 2] = d * (A[:, 0, 2] + self.problem.bf * iz * iz)
        sw = np.sqrt(w)
        A *= (sw / self.sigma)[:, None, None]
        e = e * sw[:, None]
        # the pose perturbed on the right, T exp(d) with d = (rotation, translation): dp/dd = [[p]x, -I]
        Jc = np.concatenate([_nn(A, _skew(p)), -A], axis=2)  # (n, 3, 6)
        Jp = _nn(A, RT)  # dp/dX = R^T
        V = _segment_sum(_tn(Jp, Jp), self.pt_order, self.pt_starts)
        gp = _segment_sum(_tv(Jp, e), self.pt_order, self.pt_starts)
        fm = self.fm
        Jc, Jpf, ef = Jc[fm], Jp[fm], e[fm]
        U = np.add.reduceat(_tn(Jc, Jc), self.fm_cam_starts, axis=0) if fm.size else None
        gc = np.add.reduceat(_tv(Jc, ef), self.fm_cam_starts, axis=0) if fm.size else None
        W = _tn(Jc, Jpf)  # camera-point blocks of the free cameras' observations, in `fm` order
        cross = self.gyro.add_to(gyro_state, U, gc) if U is not None else []
        return U, V, W, gc, gp, cross

    def _sum_free_by_point(self, values: np.ndarray) -> np.ndarray:
        """Per point: the sum of `values` (one row per free-camera observation, in `fm` order)."""
        out = np.zeros((self.pts.size,) + values.shape[1:])
        if values.shape[0]:
            out[self.fm_pts] = _segment_sum(values, self.fm_pt_order, self.fm_pt_starts)
        return out

    def step(self, eqs, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Camera and point increments of the damped system, the points eliminated first."""
        U, V, W, gc, gp, cross = eqs
        nf, fm = self.free.size, self.fm
        D = _inverse_cholesky3(V + lam * np.eye(3))  # V^-1 = D^T D, per point
        if nf == 0:
            return np.zeros((0, 6)), _tv(D, _mv(D, -gp))
        # reduced camera system S dc = b: S = U - sum W V^-1 W^T = U - G G^T with G = W D^T per
        # observation, b = -gc + sum W V^-1 gp = -gc + sum G (D gp)
        G = _nt(W, D[self.pt[fm]])  # (free observations, 6, 3)
        Dg = _mv(D, gp)
        b = -gc + np.add.reduceat(_mv(G, Dg[self.pt[fm]]), self.fm_cam_starts, axis=0)
        if self.dense:
            Gd = np.zeros((nf, 6, self.pts.size, 3))
            Gd[self.cam[fm], :, self.pt[fm], :] = G
            Gd = Gd.reshape(6 * nf, 3 * self.pts.size)
            S = -(Gd @ Gd.T)
        else:  # scipy's sparse product: sequential sums in the CSR order, no threads
            import scipy.sparse  # lazy: ~0.15 s to import, for the back end's process, not the tracker's

            Gs = scipy.sparse.csr_matrix((self._csr_data(G), self.csr_indices, self.csr_indptr),
                                         shape=(6 * nf, 3 * self.pts.size))
            S = -(Gs @ Gs.T).toarray()
        blocks = S.reshape(nf, 6, nf, 6)
        for c in range(nf):
            blocks[c, :, c, :] += U[c] + lam * np.eye(6)
        for ca, cb, block in cross:
            blocks[ca, :, cb, :] += block
            blocks[cb, :, ca, :] += block.T
        dc = np.linalg.solve(S, b.reshape(-1)).reshape(nf, 6)
        # back-substitution: dX = V^-1 (-gp - sum W^T dc)
        Wtd = _tv(W, dc[self.cam[fm]])
        return dc, _tv(D, _mv(D, -gp - self._sum_free_by_point(Wtd)))

    def apply(self, poses: np.ndarray, X: np.ndarray, dc: np.ndarray, dX: np.ndarray):
        poses = poses.copy()
        X = X.copy()
        for c, i in enumerate(self.free.tolist()):
            R = poses[i, :3, :3].copy()
            poses[i, :3, 3] += R @ dc[c, 3:]
            poses[i, :3, :3] = R @ so3_exp(dc[c, :3])
        X[self.pts] += dX
        return poses, X


def _levenberg_marquardt(problem: BundleProblem, ms: np.ndarray, poses: np.ndarray, X: np.ndarray,
                         iterations: int) -> tuple[np.ndarray, np.ndarray, int, float, float]:
    s = _Solve(problem, ms)
    cost, state = s.residuals(poses, X)
    before = cost
    lam = LAMBDA_START
    done = 0
    for _ in range(iterations):
        eqs = s.normal_equations(state)
        done += 1
        while lam <= LAMBDA_MAX:
            try:
                dc, dX = s.step(eqs, lam)
            except np.linalg.LinAlgError:
                lam *= LAMBDA_FACTOR
                continue
            new_poses, new_X = s.apply(poses, X, dc, dX)
            new_cost, new_state = s.residuals(new_poses, new_X)
            if new_cost < cost:
                break
            lam *= LAMBDA_FACTOR
        else:
            break  # no damping helps: at a minimum (or a degenerate system)
        decrease = (cost - new_cost) / max(cost, 1e-300)
        poses, X, cost, state = new_poses, new_X, new_cost, new_state
        lam = max(lam / LAMBDA_FACTOR, 1e-12)
        if decrease < RELATIVE_DECREASE:
            break
    return poses, X, done, before, cost


def bundle_adjust(problem: BundleProblem, *, iterations: int = 5) -> BundleResult:
    """Bundle adjustment; fixed keyframes anchor the gauge and do not move. Deterministic for equal input."""
    # Points need two observations to move anything; keyframes need observations to be solvable.
    n_obs = np.bincount(problem.obs_pt, minlength=len(problem.points))
    active = n_obs[problem.obs_pt] >= 2
    thr = np.where(problem.obs_z > 0, CHI2_3DOF, CHI2_2DOF)
    if not np.any(active) or np.all(problem.fixed[np.unique(problem.obs_kf[active])]):
        inl = observation_chi2(problem, problem.poses_wc, problem.points) <= thr
        return BundleResult(problem.poses_wc.copy(), problem.points.copy(), inl, 0, 0.0, 0.0)
    poses, pts, it1, before, _ = _levenberg_marquardt(problem, np.flatnonzero(active), problem.poses_wc,
                                                      problem.points, iterations)
    inl = observation_chi2(problem, poses, pts) <= thr
    active2 = active & inl
    n_obs2 = np.bincount(problem.obs_pt[active2], minlength=len(problem.points))
    active2 &= n_obs2[problem.obs_pt] >= 2
    it2, after = 0, 0.0
    if np.any(active2) and not np.all(problem.fixed[np.unique(problem.obs_kf[active2])]):
        poses, pts, it2, _, after = _levenberg_marquardt(problem, np.flatnonzero(active2), poses, pts, iterations)
    inl = observation_chi2(problem, poses, pts) <= thr
    return BundleResult(poses, pts, inl, it1 + it2, float(before), float(after))
