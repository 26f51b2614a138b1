"""Bundle adjustment in NumPy (tracker/bundle.py) against gtsam, which did it before and still solves
the pose graph: the same model (stereo + mono observations, Huber, fixed keyframes, two passes with
outliers dropped between them) must reach the same optimum."""

from __future__ import annotations

import math

import numpy as np
import pytest

from octolog.tracker import bundle
from octolog.tracker.bundle import BundleProblem, bundle_adjust, observation_chi2
from octolog.tracker.pose import CHI2_2DOF, CHI2_3DOF, rotation_angle, so3_exp

K = (520.0, 515.0, 318.0, 243.0)


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(rotvec, float))
    T[:3, 3] = t
    return T


def _problem(seed: int, *, n_kf: int = 6, n_fixed: int = 2, n_pts: int = 400, mono: float = 0.1,
             outliers: int = 40) -> tuple[BundleProblem, list[np.ndarray]]:
    """Keyframes on an arc looking at a wall of points: noisy pixels and depths, some observations
    without depth, some gross outliers, the free keyframes and every point perturbed."""
    rng = np.random.default_rng(seed)
    truth = [_pose([0.0, 0.03 * i, 0.01 * i], [0.08 * i, 0.01 * i, 0.0]) for i in range(n_kf)]
    X = rng.uniform([-1.5, -1.0, 2.0], [1.5, 1.0, 4.5], (n_pts, 3))
    kf, pt, uv, z, sig = [], [], [], [], []
    for i, T in enumerate(truth):
        seen = np.flatnonzero(rng.random(n_pts) < 0.8)
        p = (X[seen] - T[:3, 3]) @ T[:3, :3]
        u = np.stack([K[0] * p[:, 0] / p[:, 2] + K[2], K[1] * p[:, 1] / p[:, 2] + K[3]], axis=1)
        octave = rng.integers(0, 4, seen.size)
        s = 1.2 ** octave
        kf += [i] * seen.size
        pt += seen.tolist()
        uv.append(u + rng.normal(0, 1, u.shape) * s[:, None] * 0.5)
        d = p[:, 2] * (1 + rng.normal(0, 0.003, seen.size))
        d[rng.random(seen.size) < mono] = 0.0
        z.append(d)
        sig.append(s)
    uv, z = np.concatenate(uv), np.concatenate(z)
    bad = rng.choice(uv.shape[0], outliers, replace=False)
    uv[bad] += rng.uniform(25, 60, (outliers, 2))
    start = [T if i < n_fixed else T @ _pose(rng.normal(0, 0.01, 3), rng.normal(0, 0.02, 3))
             for i, T in enumerate(truth)]
    problem = BundleProblem(
        poses_wc=np.stack(start), fixed=np.arange(n_kf) < n_fixed, points=X + rng.normal(0, 0.02, X.shape),
        obs_kf=np.array(kf), obs_pt=np.array(pt), obs_uv=uv, obs_z=z, obs_sigma=np.concatenate(sig), K=K, bf=40.0)
    return problem, truth


def _gtsam_reference(problem: BundleProblem, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """The same two-pass bundle adjustment with gtsam's factors and optimiser (the earlier implementation)."""
    gtsam = pytest.importorskip("gtsam")
    fx, fy, cx, cy = problem.K
    cal_s = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, problem.bf / fx)
    cal_m = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
    thr = np.where(problem.obs_z > 0, CHI2_3DOF, CHI2_2DOF)

    def pose3(T):
        return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), gtsam.Point3(*T[:3, 3]))

    def solve(active, poses, pts):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        X = lambda i: gtsam.symbol("x", int(i))  # noqa: E731
        L = lambda j: gtsam.symbol("l", int(j))  # noqa: E731
        for i in np.unique(problem.obs_kf[active]):
            values.insert(X(i), pose3(poses[i]))
            if problem.fixed[i]:
                graph.add(gtsam.NonlinearEqualityPose3(X(i), pose3(poses[i])))
        for j in np.unique(problem.obs_pt[active]):
            values.insert(L(j), gtsam.Point3(*pts[j]))
        for m in np.flatnonzero(active):
            i, j, (u, v), z, s = problem.obs_kf[m], problem.obs_pt[m], problem.obs_uv[m], problem.obs_z[m], \
                problem.obs_sigma[m]
            stereo = z > 0
            base = gtsam.noiseModel.Isotropic.Sigma(3 if stereo else 2, s)
            k = math.sqrt(CHI2_3DOF if stereo else CHI2_2DOF)
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
            if stereo:
                graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, u - problem.bf / z, v), noise, X(i), L(j),
                                                      cal_s))
            else:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(u, v), noise, X(i), L(j), cal_m))
        for (a, b), R, sigma in zip(problem.rot_pairs, problem.rot_ab, problem.rot_sigma):
            # a rotation-only factor: a pose between factor whose translation is free (its whitened
            # error is negligible), the rotation part of Pose3's log being the rotation's log
            base = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sigma), np.full(3, 1e6)])
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(math.sqrt(CHI2_3DOF)), base)
            graph.add(gtsam.BetweenFactorPose3(X(a), X(b), gtsam.Pose3(gtsam.Rot3(R), gtsam.Point3(0, 0, 0)), noise))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iterations)
        out = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        poses = poses.copy()
        pts = pts.copy()
        for i in np.unique(problem.obs_kf[active]):
            poses[i] = out.atPose3(X(i)).matrix()
        for j in np.unique(problem.obs_pt[active]):
            pts[j] = out.atPoint3(L(j))
        return poses, pts

    n_obs = np.bincount(problem.obs_pt, minlength=len(problem.points))
    active = n_obs[problem.obs_pt] >= 2
    poses, pts = solve(active, problem.poses_wc, problem.points)
    active &= observation_chi2(problem, poses, pts) <= thr
    active &= np.bincount(problem.obs_pt[active], minlength=len(problem.points))[problem.obs_pt] >= 2
    return solve(active, poses, pts)


def _assert_same_optimum(ours, ref_poses: np.ndarray, ref_pts: np.ndarray) -> None:
    """Poses within 10 µm / 1e-5 of rotation of gtsam's, points within 10 µm (median)."""
    for i in range(len(ref_poses)):
        assert np.linalg.norm(ours.poses_wc[i][:3, 3] - ref_poses[i][:3, 3]) < 1e-5, i
        assert np.abs(ours.poses_wc[i][:3, :3] - ref_poses[i][:3, :3]).max() < 1e-5, i
    assert np.median(np.linalg.norm(ours.points - ref_pts, axis=1)) < 1e-5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numpy_bundle_adjustment_reaches_gtsams_optimum(seed: int) -> None:
    problem, truth = _problem(seed)
    ours = bundle_adjust(problem, iterations=20)
    ref_poses, ref_pts = _gtsam_reference(problem, iterations=20)
    _assert_same_optimum(ours, ref_poses, ref_pts)
    # and the optimum is the truth, within the noise (the start was 1-2 cm off)
    assert max(np.linalg.norm(ours.poses_wc[i][:3, 3] - truth[i][:3, 3]) for i in range(len(truth))) < 0.005
    np.testing.assert_array_equal(ours.poses_wc[:2], problem.poses_wc[:2])  # fixed keyframes do not move


def test_dense_and_sparse_reduced_systems_agree(monkeypatch) -> None:
    """A local BA forms the reduced camera system by one dense product, a large final BA by a sparse
    one: the two must give the same answer."""
    problem, _ = _problem(3, n_kf=8, n_pts=300)
    dense = bundle_adjust(problem, iterations=10)
    monkeypatch.setattr(bundle, "DENSE_MAX_CELLS", 0)
    sparse = bundle_adjust(problem, iterations=10)
    np.testing.assert_allclose(sparse.poses_wc, dense.poses_wc, atol=1e-9)
    np.testing.assert_allclose(sparse.points, dense.points, atol=1e-8)
    np.testing.assert_array_equal(sparse.inliers, dense.inliers)


def test_a_keyframe_that_sees_a_point_twice_reaches_gtsams_optimum() -> None:
    """Two keypoints of one keyframe matched to one map point: two observations of the same
    (camera, point) cell, whose blocks the sparse reduced system must sum, as gtsam's two factors do."""
    problem, _ = _problem(5)
    rng = np.random.default_rng(5)
    free = np.flatnonzero(~problem.fixed[problem.obs_kf])
    dup = np.sort(rng.choice(free, 60, replace=False))
    cat = lambda a: np.concatenate([a, a[dup]])  # noqa: E731
    problem = BundleProblem(
        poses_wc=problem.poses_wc, fixed=problem.fixed, points=problem.points, obs_kf=cat(problem.obs_kf),
        obs_pt=cat(problem.obs_pt), obs_uv=cat(problem.obs_uv) + np.r_[np.zeros_like(problem.obs_uv),
                                                                         rng.normal(0, 0.7, (dup.size, 2))],
        obs_z=cat(problem.obs_z), obs_sigma=cat(problem.obs_sigma), K=problem.K, bf=problem.bf)
    ours = bundle_adjust(problem, iterations=20)
    ref_poses, ref_pts = _gtsam_reference(problem, iterations=20)
    _assert_same_optimum(ours, ref_poses, ref_pts)


def test_a_point_behind_a_camera_is_an_outlier_not_a_crash() -> None:
    problem, _ = _problem(4, outliers=0)
    X = problem.points.copy()
    behind = problem.obs_pt[problem.obs_kf == 3][0]
    T = problem.poses_wc[3]
    X[behind] = T[:3, 3] - 2.0 * T[:3, 2]  # 2 m behind keyframe 3
    res = bundle_adjust(BundleProblem(**{**problem.__dict__, "points": X}), iterations=10)
    assert np.all(np.isfinite(res.poses_wc)) and np.all(np.isfinite(res.points))
    seen_behind = (problem.obs_pt == behind) & (problem.obs_kf == 3)
    assert not res.inliers[seen_behind].any()
    assert res.error_after < res.error_before


def test_bundle_adjustment_is_byte_identical_run_to_run() -> None:
    problem, _ = _problem(5)
    a, b = bundle_adjust(problem, iterations=10), bundle_adjust(problem, iterations=10)
    assert a.poses_wc.tobytes() == b.poses_wc.tobytes() and a.points.tobytes() == b.points.tobytes()


def _with_gyro(problem: BundleProblem, truth: list[np.ndarray], sigma: float, seed: int) -> BundleProblem:
    """The problem with the gyro's rotation between consecutive keyframes: the truth's, off by sigma."""
    rng = np.random.default_rng(seed)
    pairs = np.array([(i, i + 1) for i in range(len(truth) - 1)], np.int64)
    rot = np.stack([truth[a][:3, :3].T @ truth[b][:3, :3] @ so3_exp(rng.normal(0, sigma, 3)) for a, b in pairs])
    return BundleProblem(**{**problem.__dict__, "rot_pairs": pairs, "rot_ab": rot,
                            "rot_sigma": np.full(len(pairs), sigma)})


def test_the_gyros_rotations_between_keyframes_reach_gtsams_optimum() -> None:
    """Keyframe rotation factors (tracker/inertial.py: Inertial.keyframe_rotation) in the same
    optimum as gtsam's between factors on the rotation, dense and sparse."""
    problem, truth = _problem(6)
    problem = _with_gyro(problem, truth, np.radians(0.05), 6)
    ours = bundle_adjust(problem, iterations=20)
    ref_poses, ref_pts = _gtsam_reference(problem, iterations=20)
    _assert_same_optimum(ours, ref_poses, ref_pts)


def test_the_gyro_holds_keyframes_that_vision_sees_poorly() -> None:
    """With a handful of points, the free keyframes' rotations come out within the gyro's error
    chained from the fixed keyframes, and at least twice closer to the truth than vision's alone."""
    problem, truth = _problem(7, n_pts=25, outliers=0)
    sigma = np.radians(0.02)

    def worst(poses: np.ndarray) -> float:
        return max(rotation_angle(truth[i][:3, :3].T @ poses[i][:3, :3]) for i in range(len(truth)))
    vision = worst(bundle_adjust(problem, iterations=20).poses_wc)
    fused = worst(bundle_adjust(_with_gyro(problem, truth, sigma, 7), iterations=20).poses_wc)
    assert fused < 4 * sigma * np.sqrt(len(truth)) and fused < vision / 2, (np.degrees(fused), np.degrees(vision))
