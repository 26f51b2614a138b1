"""Back-end optimisation with gtsam: local bundle adjustment and keyframe pose graphs.

Both take plain arrays and return plain arrays, so they can run on any thread and be tested alone.

Local bundle adjustment models an RGB-D observation the way ORB-SLAM does: as a rectified stereo
measurement (u_left, u_right = u_left - bf / z, v) of a `gtsam.GenericStereoFactor3D`, where the
virtual baseline `bf` is chosen so that one pixel on u_right equals the tracker's inverse-depth
sigma. Keypoints without depth give a monocular `GenericProjectionFactorCal3_S2`. Every factor has
a Huber kernel at the chi-square 95% threshold, and sigma = scale_factor ** octave pixels.
As in ORB-SLAM, the optimisation runs twice: after the first run the observations that fail the
chi-square test are dropped, then it runs again without them.

gtsam is imported where it is used: the tracking process only builds problems (BundleProblem) and
leaves solving them to the back-end worker, so it does not carry gtsam's ~40 MB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from octolog.tracker.pose import CHI2_2DOF, CHI2_3DOF

# sigma (rad, m) of the prior holding a fixed keyframe: ~200x tighter than its pose is known from ~500
# pixel observations, loose enough that the normal equations keep their precision
FIXED_SIGMA = 1e-6


@dataclass(frozen=True)
class BundleProblem:
    """Keyframes, points and observations of a local bundle adjustment (indices are local)."""

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


@dataclass(frozen=True)
class BundleResult:
    poses_wc: np.ndarray  # (K, 4, 4)
    points: np.ndarray  # (P, 3)
    inliers: np.ndarray  # (M,) bool: observations that pass the chi-square test at the end
    iterations: int
    error_before: float
    error_after: float


def _pose3(T: np.ndarray):
    import gtsam

    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), gtsam.Point3(*T[:3, 3]))


def _matrix(p) -> np.ndarray:
    return np.asarray(p.matrix(), dtype=np.float64)


def observation_chi2(problem: BundleProblem, poses_wc: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Squared whitened residual of every observation (stereo where there is depth, else mono)."""
    fx, fy, cx, cy = problem.K
    R = poses_wc[problem.obs_kf, :3, :3]
    t = poses_wc[problem.obs_kf, :3, 3]
    d = points[problem.obs_pt] - t
    p = np.einsum("nji,nj->ni", R, d)  # camera_from_world applied: R^T (X - t)
    z = p[:, 2]
    iz = 1.0 / np.where(z > 1e-6, z, 1e-6)
    u = fx * p[:, 0] * iz + cx
    v = fy * p[:, 1] * iz + cy
    e = (u - problem.obs_uv[:, 0]) ** 2 + (v - problem.obs_uv[:, 1]) ** 2
    has_d = problem.obs_z > 0
    ur_meas = problem.obs_uv[:, 0] - problem.bf / np.where(has_d, problem.obs_z, 1.0)
    e = e + np.where(has_d, (u - problem.bf * iz - ur_meas) ** 2, 0.0)
    chi2 = e / (problem.obs_sigma ** 2)
    return np.where(z > 1e-6, chi2, np.inf)


def bundle_adjust(problem: BundleProblem, *, iterations: int = 5) -> BundleResult:
    """Local bundle adjustment; fixed keyframes anchor the gauge. Deterministic for equal input."""
    import gtsam

    fx, fy, cx, cy = problem.K
    cal_s = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, problem.bf / fx)
    cal_m = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
    x_key = np.array([gtsam.symbol("x", 0)], dtype=np.uint64)[0]  # key of keyframe 0; keyframe i: + i
    l_key = np.array([gtsam.symbol("l", 0)], dtype=np.uint64)[0]
    X = (x_key + np.arange(len(problem.poses_wc), dtype=np.uint64)).tolist()
    L = (l_key + np.arange(len(problem.points), dtype=np.uint64)).tolist()
    noise: dict[tuple[bool, float], object] = {}
    fixed_noise = gtsam.noiseModel.Isotropic.Sigma(6, FIXED_SIGMA)

    def model(stereo: bool, sigma: float):
        key = (stereo, sigma)
        if key not in noise:
            base = gtsam.noiseModel.Isotropic.Sigma(3 if stereo else 2, sigma)
            k = math.sqrt(CHI2_3DOF if stereo else CHI2_2DOF)
            noise[key] = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
        return noise[key]

    factors: dict[int, object] = {}  # observation -> its factor, made once for both passes

    def factor(m: int, i: int, j: int, u: float, v: float, z: float, s: float):
        f = factors.get(m)
        if f is None:
            if z > 0:
                f = gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, u - problem.bf / z, v), model(True, s),
                                                X[i], L[j], cal_s)
            else:
                f = gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(u, v), model(False, s), X[i], L[j], cal_m)
            factors[m] = f
        return f

    def solve(active: np.ndarray, poses: np.ndarray,
              pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, float, float]:
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        used_kf = np.unique(problem.obs_kf[active]).tolist()
        used_pt = np.unique(problem.obs_pt[active]).tolist()
        for i in used_kf:
            values.insert(X[i], _pose3(poses[i]))
            if problem.fixed[i]:
                # held by a tight prior (its pose is not written back), not a NonlinearEquality: a
                # constrained factor makes gtsam eliminate its whole clique by QR instead of Cholesky,
                # which cost 4x the time and 2x the memory on a BA with 6 fixed keyframes
                graph.add(gtsam.PriorFactorPose3(X[i], _pose3(poses[i]), fixed_noise))
        for j, p in zip(used_pt, pts[used_pt].tolist()):
            values.insert(L[j], gtsam.Point3(*p))
        ms = np.flatnonzero(active)
        for m, i, j, (u, v), z, s in zip(ms.tolist(), problem.obs_kf[ms].tolist(), problem.obs_pt[ms].tolist(),
                                         problem.obs_uv[ms].tolist(), problem.obs_z[ms].tolist(),
                                         problem.obs_sigma[ms].tolist()):
            graph.add(factor(m, i, j, u, v, z, s))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iterations)
        params.setVerbosityLM("SILENT")
        # sequential elimination: on problems this small, the multifrontal solver's TBB tasks cost
        # more than they save (3x slower measured on a 2-core machine with other work on it)
        params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        before = graph.error(values)
        out = opt.optimize()
        after = graph.error(out)
        poses = poses.copy()
        pts = pts.copy()
        for i in used_kf:
            if not problem.fixed[i]:
                poses[i] = _matrix(out.atPose3(X[i]))
        for j in used_pt:
            pts[j] = out.atPoint3(L[j])
        return poses, pts, opt.iterations(), before, after

    # Points need two observations to move anything; keyframes need observations to be solvable.
    n_obs = np.bincount(problem.obs_pt, minlength=len(problem.points))
    active = n_obs[problem.obs_pt] >= 2
    if not np.any(active) or np.all(problem.fixed[np.unique(problem.obs_kf[active])]):
        chi2 = observation_chi2(problem, problem.poses_wc, problem.points)
        inl = chi2 <= np.where(problem.obs_z > 0, CHI2_3DOF, CHI2_2DOF)
        return BundleResult(problem.poses_wc.copy(), problem.points.copy(), inl, 0, 0.0, 0.0)
    poses, pts, it1, before, _ = solve(active, problem.poses_wc, problem.points)
    thr = np.where(problem.obs_z > 0, CHI2_3DOF, CHI2_2DOF)
    inl = observation_chi2(problem, poses, pts) <= thr
    active2 = active & inl
    n_obs2 = np.bincount(problem.obs_pt[active2], minlength=len(problem.points))
    active2 &= n_obs2[problem.obs_pt] >= 2
    it2, after = 0, 0.0
    if np.any(active2) and not np.all(problem.fixed[np.unique(problem.obs_kf[active2])]):
        poses, pts, it2, _, after = solve(active2, poses, pts)
    inl = observation_chi2(problem, poses, pts) <= thr
    return BundleResult(poses, pts, inl, it1 + it2, float(before), float(after))


def optimize_pose_graph(
    poses_wc: np.ndarray,
    edges: list[tuple[int, int, np.ndarray, float]],
    *,
    fixed: int = 0,
    iterations: int = 20,
) -> np.ndarray:
    """Keyframe poses that best agree with relative-pose edges (i, j, T_i_j = inv(T_wi) T_wj, weight).

    Edge noise: 1 cm and 0.5 degree divided by sqrt(weight). Keyframe `fixed` does not move.
    """
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, T in enumerate(poses_wc):
        values.insert(i, _pose3(T))
    graph.add(gtsam.NonlinearEqualityPose3(fixed, _pose3(poses_wc[fixed])))
    base = np.array([math.radians(0.5)] * 3 + [0.01] * 3)
    for i, j, T_ij, w in edges:
        graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_ij),
                                           gtsam.noiseModel.Diagonal.Sigmas(base / math.sqrt(max(w, 1e-6)))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    out = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.stack([_matrix(out.atPose3(i)) for i in range(len(poses_wc))])
