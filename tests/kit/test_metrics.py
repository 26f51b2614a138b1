"""Tests for octolog.metrics: TUM I/O, association, Umeyama, ATE/RPE (checked against evo)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from octolog.kit.errors import InputError
from octolog.kit.metrics import (
    Trajectory,
    associate,
    ate,
    format_report,
    format_tum,
    read_tum,
    rpe,
    umeyama_se3,
    write_tum,
)

evo_sync = pytest.importorskip("evo.core.sync")
evo_metrics = pytest.importorskip("evo.core.metrics")
from evo.core.metrics import PoseRelation, Unit  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402

REL_TOL = 1e-9
TUM_SUBDIR = Path("tum/rgbd_dataset_freiburg1_xyz_first300/groundtruth.txt")


# --------------------------------------------------------------------------------- helpers


def smooth_trajectory(
    rng: np.random.Generator, stamps_ns: np.ndarray, *, t0_ns: int | None = None, n_terms: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth random positions (N,3) and quaternions xyzw (N,4) at the given stamps.

    The curve depends only on the rng state and t0_ns (default: the first stamp).
    """
    t = (stamps_ns - (stamps_ns[0] if t0_ns is None else t0_ns)) / 1e9
    pos = np.zeros((t.size, 3))
    rotvec = np.zeros((t.size, 3))
    for _ in range(n_terms):
        f = rng.uniform(0.05, 0.5, size=3)
        ph = rng.uniform(0, 2 * np.pi, size=3)
        pos += rng.uniform(0.2, 1.0, size=3) * np.sin(2 * np.pi * f * t[:, None] + ph)
        rotvec += rng.uniform(0.1, 0.4, size=3) * np.sin(2 * np.pi * f[::-1] * t[:, None] + ph)
    return pos, Rotation.from_rotvec(rotvec).as_quat()


def stamps(
    rng: np.random.Generator, start_ns: int, n: int, period_ns: int, jitter_ns: int
) -> np.ndarray:
    """Increasing stamps with uniform jitter (kept far from any association threshold)."""
    base = start_ns + np.arange(n, dtype=np.int64) * period_ns
    return base + rng.integers(-jitter_ns, jitter_ns + 1, size=n)


def jitter_rotation(rng: np.random.Generator, n: int, sigma_rad: float) -> Rotation:
    """n small random rotations (rotation vectors ~ N(0, sigma^2 I3))."""
    return Rotation.from_rotvec(rng.normal(0, sigma_rad, (n, 3)))


def transform(traj: Trajectory, T: np.ndarray) -> Trajectory:
    """World-frame rigid transform of every pose: T @ P_i."""
    return Trajectory.from_matrices(traj.stamps_ns, T[None] @ traj.matrices())


def random_rigid(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-5, 5, size=3)
    return T


def to_evo(traj: Trajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(
        positions_xyz=traj.positions.copy(),
        orientations_quat_wxyz=np.roll(traj.quats_xyzw, 1, axis=1),
        timestamps=traj.stamps_ns / 1e9,
    )


def evo_ate(est: Trajectory, gt: Trajectory) -> tuple[dict[str, float], np.ndarray, int]:
    ref, e = evo_sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=0.02)
    r, t, _ = e.align(ref, correct_scale=False)
    ape = evo_metrics.APE(PoseRelation.translation_part)
    ape.process_data((ref, e))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = r, t
    return ape.get_all_statistics(), T, ref.num_poses


def evo_rpe(
    est: Trajectory, gt: Trajectory, relation: PoseRelation, delta: int = 1, all_pairs: bool = False
) -> tuple[dict[str, float], int]:
    ref, e = evo_sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=0.02)
    m = evo_metrics.RPE(relation, delta=delta, delta_unit=Unit.frames, all_pairs=all_pairs)
    m.process_data((ref, e))
    return m.get_all_statistics(), len(m.error)


def assert_rel(ours: float, ref: float, tol: float = REL_TOL) -> None:
    assert ours == pytest.approx(ref, rel=tol, abs=1e-15), (ours, ref)


@pytest.fixture()
def pair() -> tuple[Trajectory, Trajectory]:
    """Ground truth at ~100 Hz and a noisy, rigidly offset estimate at ~30 Hz."""
    rng = np.random.default_rng(7)
    t0 = 1_305_031_101_165_900_000
    gt_st = stamps(rng, t0, 1200, 10_000_000, 1_000_000)
    gp, gq = smooth_trajectory(np.random.default_rng(99), gt_st, t0_ns=t0)
    gt = Trajectory(gt_st, gp, gq)
    est_st = stamps(rng, t0 + 3_000_000, 380, 33_333_333, 2_000_000)
    # Same curve at the estimate's stamps (within 20 ms of gt: the curve moves ~mm meanwhile).
    ep, eq = smooth_trajectory(np.random.default_rng(99), est_st, t0_ns=t0)
    ep = ep + rng.normal(0, 0.01, ep.shape)
    eq = (jitter_rotation(rng, len(eq), 0.005) * Rotation.from_quat(eq)).as_quat()
    est = transform(Trajectory(est_st, ep, eq), random_rigid(rng))
    return est, gt


# --------------------------------------------------------------------------------- TUM I/O


def test_parse_exact_stamps_comments_and_blank_lines(tmp_path: Path) -> None:
    p = tmp_path / "gt.txt"
    p.write_text(
        "# ground truth trajectory\n\n"
        "1305031101.1659 1.3800 0.6185 1.6972 0.6522 0.6187 -0.2952 -0.3236\n"
        "   \n"
        "1305031101.175900001\t1.3812 0.6186 1.6987 0.6520 0.6182 -0.2954 -0.3248  \n"
        "  # indented comment\n"
        "17 0 0 0 0 0 0 1\n"
    )
    traj = read_tum(p)
    assert traj.stamps_ns.dtype == np.int64
    assert traj.stamps_ns.tolist() == [1305031101165900000, 1305031101175900001, 17_000_000_000]
    np.testing.assert_array_equal(traj.positions[0], [1.38, 0.6185, 1.6972])
    np.testing.assert_array_equal(traj.quats_xyzw[1], [0.6520, 0.6182, -0.2954, -0.3248])
    assert len(traj) == 3


def test_write_read_round_trip_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    st = stamps(rng, 1_600_000_000_000_000_000, 200, 33_333_333, 5_000_000)
    st[0] = 5  # a stamp below one second still prints as 0.000000005
    pos, q = smooth_trajectory(rng, st)
    pos *= 50.0
    poses = Trajectory(st, pos, q).matrices()
    p = tmp_path / "est.txt"
    write_tum(p, st, poses)
    text = p.read_text()
    assert text.splitlines()[0].startswith("0.000000005 ")
    back = read_tum(p)
    np.testing.assert_array_equal(back.stamps_ns, st)  # stamps exact
    np.testing.assert_allclose(back.positions, pos, rtol=0, atol=5e-10)
    assert np.all(back.quats_xyzw[:, 3] >= 0)
    d = Rotation.from_quat(back.quats_xyzw).inv() * Rotation.from_matrix(poses[:, :3, :3])
    assert np.max(d.magnitude()) < 1e-8
    # Text is a fixed point: re-writing what was read reproduces the file byte for byte.
    assert format_tum(back.stamps_ns, back) == text
    assert format_tum(back.stamps_ns, np.hstack([back.positions, back.quats_xyzw])) == text
    write_tum(tmp_path / "again.txt", back.stamps_ns, back)
    assert (tmp_path / "again.txt").read_bytes() == p.read_bytes()


def test_format_is_deterministic_and_canonical() -> None:
    T = np.eye(4)
    T[:3, 3] = [-1e-12, 1.0, -2.5]
    line = format_tum(np.array([1_305_031_101_165_900_000]), T[None])
    assert line == (
        "1305031101.165900000 0.000000000 1.000000000 -2.500000000"
        " 0.000000000 0.000000000 0.000000000 1.000000000\n"
    )
    rows = np.array([[0, 0, 0, 0.0, 0.0, 0.0, -1.0], [0, 0, 0, -1.0, 0.0, 0.0, 0.0]])
    out = format_tum(np.array([1, 2]), rows).splitlines()
    assert out[0].endswith(" 0.000000000 0.000000000 0.000000000 1.000000000")
    assert out[1].endswith(" 1.000000000 0.000000000 0.000000000 0.000000000")


@pytest.mark.parametrize(
    ("content", "lineno", "problem"),
    [
        ("# c\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n", 3, "expected 8 values"),
        ("1.0 0 0 0 0 0 0 1\n\nabc 0 0 0 0 0 0 1\n", 3, "bad timestamp"),
        ("1.0 0 0 x 0 0 0 1\n", 1, "non-numeric"),
        ("1.0 0 0 nan 0 0 0 1\n", 1, "non-finite"),
        ("1.0 0 0 0 0 0 0 0\n", 1, "zero quaternion"),
        ("1.0,0,0,0,0,0,0,1\n", 1, "expected 8 values"),
    ],
)
def test_bad_file_reports_path_and_line(
    tmp_path: Path, content: str, lineno: int, problem: str
) -> None:
    p = tmp_path / "bad.txt"
    p.write_text(content)
    with pytest.raises(InputError, match=problem) as info:
        read_tum(p)
    assert str(info.value).startswith(f"{p}:{lineno}: ")


@pytest.mark.parametrize("content", ["", "# only a comment\n\n"])
def test_empty_file_is_input_error(tmp_path: Path, content: str) -> None:
    p = tmp_path / "empty.txt"
    p.write_text(content)
    with pytest.raises(InputError, match=str(p)):
        read_tum(p)


def test_missing_file_is_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="missing.txt"):
        read_tum(tmp_path / "missing.txt")


# --------------------------------------------------------------------------------- association


def test_associate_nearest_within_threshold() -> None:
    a = np.array([0, 100, 200, 300, 1000], dtype=np.int64)
    b = np.array([5, 95, 180, 320, 5000], dtype=np.int64)
    ia, ib = associate(a, b, max_dt_ns=10)
    assert list(zip(ia.tolist(), ib.tolist())) == [(0, 0), (1, 1)]
    ia, ib = associate(a, b, max_dt_ns=20)  # inclusive bound
    assert list(zip(ia.tolist(), ib.tolist())) == [(0, 0), (1, 1), (2, 2), (3, 3)]


def test_associate_is_one_to_one() -> None:
    a = np.array([100, 104, 108], dtype=np.int64)
    b = np.array([0, 105, 1000, 2000], dtype=np.int64)  # a is shorter: each a claims b[1]
    ia, ib = associate(a, b, max_dt_ns=20)
    assert ia.tolist() == [1] and ib.tolist() == [1]


def test_associate_tie_takes_earlier_and_empty_inputs() -> None:
    ia, ib = associate(np.array([0, 10, 20]), np.array([15]), max_dt_ns=10)
    assert ia.tolist() == [1] and ib.tolist() == [0]
    ia, ib = associate(np.array([], dtype=np.int64), np.array([1, 2]))
    assert ia.size == 0 and ib.size == 0


def test_associate_matches_evo_matching() -> None:
    """Same pairs as evo's nearest-time association, after dropping evo's double claims."""
    rng = np.random.default_rng(11)
    n_identical = 0
    for _ in range(40):
        a = stamps(rng, 10**18, int(rng.integers(5, 200)), 33_333_333, 3_000_000)
        b_start = 10**18 + int(rng.integers(-(10**8), 10**8))
        b = stamps(rng, b_start, int(rng.integers(5, 300)), 10_000_000, 500_000)
        ia, ib = associate(a, b)
        # evo.core.sync.associate_trajectories(a, b) starts from the shorter (b on ties).
        short_is_a = b.size > a.size
        s, l = (a, b) if short_is_a else (b, a)
        i_s, i_l = evo_sync.matching_time_indices(s / 1e9, l / 1e9, max_diff=0.02)
        best: dict[int, tuple[int, int]] = {}
        for i, j in zip(i_s, i_l):
            key = (abs(int(s[i]) - int(l[j])), i)
            if j not in best or key < best[j]:
                best[j] = key
        ref = sorted((i, j) if short_is_a else (j, i) for j, (_, i) in best.items())
        assert list(zip(ia.tolist(), ib.tolist())) == ref
        if len(set(i_l)) == len(i_l):
            n_identical += 1
            assert len(ref) == len(i_s)
    assert n_identical >= 10  # many cases where evo itself is already one-to-one


# --------------------------------------------------------------------------------- Umeyama / ATE


def test_umeyama_recovers_rigid_transform() -> None:
    rng = np.random.default_rng(5)
    src = rng.normal(size=(50, 3))
    T = random_rigid(rng)
    R, t = umeyama_se3(src, src @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t, T[:3, 3], atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_degenerate_raises() -> None:
    same = np.tile([1.0, 2.0, 3.0], (10, 1))  # rank-0 covariance (evo raises too)
    with pytest.raises(InputError, match="degenerate"):
        umeyama_se3(same, same + 1.0)


def test_ate_of_rigidly_offset_estimate_is_zero() -> None:
    rng = np.random.default_rng(1)
    st = stamps(rng, 10**18, 300, 33_333_333, 0)
    gt = Trajectory(st, *smooth_trajectory(rng, st))
    T = random_rigid(rng)
    est = transform(gt, T)
    res = ate(est, gt)
    assert res.n_pairs == 300
    assert res.rmse < 1e-9 and res.max < 1e-9
    np.testing.assert_allclose(res.alignment, np.linalg.inv(T), atol=1e-9)
    r = rpe(est, gt)
    assert r.n_pairs == 299 and r.trans_rmse < 1e-9 and r.rot_rmse_deg < 1e-5


def test_ate_of_noisy_estimate_has_expected_size() -> None:
    rng = np.random.default_rng(2)
    sigma = 0.02
    st = stamps(rng, 10**18, 2000, 33_333_333, 0)
    gt = Trajectory(st, *smooth_trajectory(rng, st))
    noisy = Trajectory(st, gt.positions + rng.normal(0, sigma, gt.positions.shape), gt.quats_xyzw)
    res = ate(transform(noisy, random_rigid(rng)), gt)
    # |N(0, sigma^2 I3)| has RMS sigma*sqrt(3); alignment absorbs only 6 of 3N dof.
    assert res.rmse == pytest.approx(sigma * np.sqrt(3), rel=0.05)
    assert res.min <= res.median <= res.max and res.std > 0
    # Translational RPE of independent noise: difference of two noises, RMS ~ sigma*sqrt(6).
    r = rpe(noisy, gt)
    assert r.trans_rmse == pytest.approx(sigma * np.sqrt(6), rel=0.05)


def test_ate_without_matches_is_input_error() -> None:
    st = np.arange(10, dtype=np.int64) * 10**9
    pos = np.random.default_rng(0).normal(size=(10, 3))
    gt = Trajectory(st, pos, np.tile([0, 0, 0, 1.0], (10, 1)))
    est = Trajectory(st + 5 * 10**8, gt.positions, gt.quats_xyzw)
    with pytest.raises(InputError, match="20 ms"):
        ate(est, gt)


def test_ate_agrees_with_evo(pair: tuple[Trajectory, Trajectory]) -> None:
    est, gt = pair
    res = ate(est, gt)
    stats, T, n = evo_ate(est, gt)
    assert res.n_pairs == n > 350
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert_rel(getattr(res, key), stats[key])
    np.testing.assert_allclose(res.alignment, T, rtol=0, atol=1e-9)
    assert 0.01 < res.rmse < 0.03  # noise sigma 1 cm per axis -> ~1.7 cm


def test_sim3_ate_and_scale_agree_with_evo(pair: tuple[Trajectory, Trajectory]) -> None:
    """A trajectory 1.5 % too long: Sim(3) alignment gives the scale that undoes it, as evo does."""
    est, gt = pair
    longer = Trajectory(est.stamps_ns, est.positions * 1.015, est.quats_xyzw)
    res = ate(longer, gt, correct_scale=True)
    ref, e = evo_sync.associate_trajectories(to_evo(gt), to_evo(longer), max_diff=0.02)
    _, _, scale = e.align(ref, correct_scale=True)
    ape = evo_metrics.APE(PoseRelation.translation_part)
    ape.process_data((ref, e))
    assert_rel(res.scale, scale)
    assert_rel(res.rmse, ape.get_all_statistics()["rmse"])
    assert abs(res.scale * 1.015 - 1) < 0.005  # the noise moves it a little
    assert ate(longer, gt).rmse > res.rmse  # SE(3) cannot take the length out


@pytest.mark.parametrize(("delta", "all_pairs"), [(1, False), (1, True), (5, False), (5, True)])
def test_rpe_agrees_with_evo(
    pair: tuple[Trajectory, Trajectory], delta: int, all_pairs: bool
) -> None:
    est, gt = pair
    res = rpe(est, gt, delta=delta, all_pairs=all_pairs)
    t_stats, n_t = evo_rpe(est, gt, PoseRelation.translation_part, delta, all_pairs)
    r_stats, n_r = evo_rpe(est, gt, PoseRelation.rotation_angle_deg, delta, all_pairs)
    assert res.n_pairs == n_t == n_r
    assert_rel(res.trans_rmse, t_stats["rmse"])
    assert_rel(res.trans_mean, t_stats["mean"])
    assert_rel(res.trans_median, t_stats["median"])
    assert_rel(res.trans_max, t_stats["max"])
    # Rotation angles are small (~0.5 deg); compare with an absolute floor for rotvec round-off.
    for key in ("rmse", "mean", "median", "max"):
        ours = getattr(res, f"rot_{key}_deg")
        assert ours == pytest.approx(r_stats[key], rel=REL_TOL, abs=1e-10)


def test_format_report(pair: tuple[Trajectory, Trajectory]) -> None:
    est, gt = pair
    a, r = ate(est, gt), rpe(est, gt)
    text = format_report(a, r)
    lines = text.splitlines()
    assert len(lines) == 3
    assert lines[0].startswith(f"ATE RMSE {a.rmse * 100:.2f} cm (n={a.n_pairs};")
    assert lines[1].startswith(
        f"RPE trans RMSE {r.trans_rmse * 100:.2f} cm per frame (n={r.n_pairs};"
    )
    assert lines[2].startswith(f"RPE rot RMSE {r.rot_rmse_deg:.3f} deg per frame")
    assert format_report(a) == lines[0]


# --------------------------------------------------------------------------------- real data


def _tum_groundtruth() -> Path:
    root = os.environ.get("OCTOLOG_DATA")
    if not root:
        pytest.skip("OCTOLOG_DATA is not set (needs <OCTOLOG_DATA>/" + str(TUM_SUBDIR) + ")")
    path = Path(root) / TUM_SUBDIR
    if not path.is_file():
        pytest.skip(f"{path} not found (OCTOLOG_DATA must hold {TUM_SUBDIR.parts[0]}/)")
    return path


def test_real_tum_groundtruth_ate_rpe_agree_with_evo(tmp_path: Path) -> None:
    from evo.tools import file_interface

    gt_path = _tum_groundtruth()
    gt = read_tum(gt_path)
    assert len(gt) > 100
    # Estimate: every 3rd ground-truth pose, 7 ms late, with position/rotation noise and a
    # rigid offset, written and read back as a TUM file.
    rng = np.random.default_rng(42)
    sub = Trajectory(gt.stamps_ns[::3] + 7_000_000, gt.positions[::3], gt.quats_xyzw[::3])
    noisy = Trajectory(
        sub.stamps_ns,
        sub.positions + rng.normal(0, 0.005, sub.positions.shape),
        (jitter_rotation(rng, len(sub), 0.003) * Rotation.from_quat(sub.quats_xyzw)).as_quat(),
    )
    est_path = tmp_path / "est.txt"
    write_tum(est_path, noisy.stamps_ns, transform(noisy, random_rigid(rng)).matrices())
    est = read_tum(est_path)

    evo_gt = file_interface.read_tum_trajectory_file(str(gt_path))
    evo_est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, e = evo_sync.associate_trajectories(evo_gt, evo_est, max_diff=0.02)
    e.align(ref, correct_scale=False)
    ape = evo_metrics.APE(PoseRelation.translation_part)
    ape.process_data((ref, e))
    ref, e = evo_sync.associate_trajectories(evo_gt, evo_est, max_diff=0.02)
    rpe_t = evo_metrics.RPE(
        PoseRelation.translation_part, delta=1, delta_unit=Unit.frames, all_pairs=False
    )
    rpe_t.process_data((ref, e))

    res = ate(est, gt)
    assert res.n_pairs == ref.num_poses == len(est)
    assert_rel(res.rmse, ape.get_statistic(evo_metrics.StatisticsType.rmse))
    assert_rel(res.max, ape.get_statistic(evo_metrics.StatisticsType.max))
    r = rpe(est, gt)
    assert_rel(r.trans_rmse, rpe_t.get_statistic(evo_metrics.StatisticsType.rmse))
    assert 0.004 < res.rmse < 0.015
