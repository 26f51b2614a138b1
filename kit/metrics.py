"""Trajectory evaluation: TUM trajectory files, association, ATE and RPE.

Pure numpy/scipy. The numbers match evo 1.38 (the reference used in the tests):

- `associate` = `evo.core.sync.associate_trajectories(traj_a, traj_b, max_diff=...)`
  with the default nearest-time method, plus one-to-one matching (see there).
- `ate` = `evo_ape tum gt.txt est.txt --align --t_max_diff 0.02`, i.e. association as above,
  `traj_est.align(traj_ref, correct_scale=False)` and
  `APE(PoseRelation.translation_part)`.
- `rpe` = `evo_rpe tum gt.txt est.txt --t_max_diff 0.02 --pose_relation trans_part
  --delta 1 --delta_unit f` (consecutive pairs; `all_pairs=True` adds `--all_pairs`),
  i.e. `RPE(PoseRelation.translation_part, delta, Unit.frames, all_pairs=...)` and the same
  with `PoseRelation.rotation_angle_deg`. RPE does not depend on a rigid alignment of the
  estimate, so none is applied.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import matrices_to_quats, quats_to_matrices

NS_PER_S = 1_000_000_000
DEFAULT_MAX_DT_NS = 20_000_000

_NS = Decimal(NS_PER_S)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Time-stamped poses (camera to world): stamps in int ns, positions (N,3), quats xyzw (N,4)."""

    stamps_ns: np.ndarray  # (N,) int64
    positions: np.ndarray  # (N, 3) float64, metres
    quats_xyzw: np.ndarray  # (N, 4) float64

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        pos = np.asarray(self.positions, dtype=float)
        quats = np.asarray(self.quats_xyzw, dtype=float)
        n = stamps.shape[0]
        if pos.shape != (n, 3) or quats.shape != (n, 4):
            raise ValueError(
                f"Trajectory shapes disagree: stamps {stamps.shape}, positions {pos.shape}, "
                f"quats {quats.shape}"
            )
        object.__setattr__(self, "stamps_ns", stamps)
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "quats_xyzw", quats)

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    @classmethod
    def from_matrices(cls, stamps_ns: np.ndarray, poses: np.ndarray) -> Trajectory:
        """Build from (N,4,4) homogeneous poses (quaternions get w >= 0)."""
        poses = _as_pose_stack(poses)
        quats = np.zeros((0, 4))
        if len(poses):
            quats = _canonical_quats(matrices_to_quats(poses[:, :3, :3]))
        return cls(np.asarray(stamps_ns, dtype=np.int64), poses[:, :3, 3].copy(), quats)

    def matrices(self) -> np.ndarray:
        """The poses as (N,4,4) homogeneous transforms."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        if len(self):
            T[:, :3, :3] = quats_to_matrices(self.quats_xyzw)
        T[:, :3, 3] = self.positions
        return T

    def subset(self, idx: np.ndarray) -> Trajectory:
        """The poses at the given indices, in that order."""
        idx = np.asarray(idx, dtype=np.intp)
        return Trajectory(self.stamps_ns[idx], self.positions[idx], self.quats_xyzw[idx])


@dataclass(frozen=True, eq=False)
class AteResult:
    """Translational absolute trajectory error (metres) after SE(3) alignment."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n_pairs: int
    alignment: np.ndarray  # (4,4): gt ~= alignment @ est
    errors: np.ndarray = field(repr=False)  # (n_pairs,) per-pair error, metres
    stamps_ns: np.ndarray = field(repr=False)  # (n_pairs,) estimate stamps of the pairs
    scale: float = 1.0  # Sim(3) alignment (`ate(correct_scale=True)`): the estimate's lengths x scale


@dataclass(frozen=True, eq=False)
class RpeResult:
    """Relative pose error over pose pairs `delta` associated frames apart."""

    trans_rmse: float  # metres
    trans_mean: float
    trans_median: float
    trans_max: float
    rot_rmse_deg: float
    rot_mean_deg: float
    rot_median_deg: float
    rot_max_deg: float
    n_pairs: int
    delta: int  # frames (associated pairs)
    trans_errors: np.ndarray = field(repr=False)  # (n_pairs,) metres
    rot_errors_deg: np.ndarray = field(repr=False)  # (n_pairs,) degrees


# ---------------------------------------------------------------------------------------------
# TUM I/O


def _parse_stamp_ns(text: str) -> int:
    """Decimal seconds -> int ns, exact up to 9 decimals, rounded half-even beyond."""
    d = Decimal(text)
    if not d.is_finite():
        raise InvalidOperation
    return int((d * _NS).to_integral_value(rounding=ROUND_HALF_EVEN))


def parse_tum(text: str, source: str = "<string>") -> Trajectory:
    """Parse TUM trajectory text ('stamp tx ty tz qx qy qz qw' per line, '#' comments)."""
    stamps: list[int] = []
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 8:
            raise InputError(
                f"{source}:{lineno}: expected 8 values 'stamp tx ty tz qx qy qz qw', "
                f"got {len(parts)}"
            )
        try:
            stamp = _parse_stamp_ns(parts[0])
        except (InvalidOperation, ValueError):
            raise InputError(f"{source}:{lineno}: bad timestamp {parts[0]!r}") from None
        try:
            vals = [float(p) for p in parts[1:]]
        except ValueError:
            raise InputError(f"{source}:{lineno}: non-numeric pose value in {line!r}") from None
        if not all(math.isfinite(v) for v in vals):
            raise InputError(f"{source}:{lineno}: non-finite pose value in {line!r}")
        if math.fsum(v * v for v in vals[3:]) < 1e-12:
            raise InputError(f"{source}:{lineno}: zero quaternion")
        stamps.append(stamp)
        rows.append(vals)
    if not rows:
        raise InputError(f"{source}: no poses (empty TUM trajectory)")
    mat = np.array(rows, dtype=float)
    return Trajectory(np.array(stamps, dtype=np.int64), mat[:, :3], mat[:, 3:])


def read_tum(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM trajectory file; malformed content raises InputError('path:lineno: ...')."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read TUM trajectory: {exc}") from None
    return parse_tum(text, str(path))


def _fmt(v: float) -> str:
    return f"{round(float(v), 9) + 0.0:.9f}"  # + 0.0 turns -0.0 into 0.0


def _canonical_quats(q: np.ndarray) -> np.ndarray:
    """Same rotations with w > 0 (or w == 0 and the first non-zero component > 0)."""
    q = np.array(q, dtype=float, copy=True)
    for row in q:
        lead = next((v for v in row[[3, 0, 1, 2]] if v != 0.0), 0.0)
        if lead < 0.0:
            row *= -1.0
    return q


def _as_pose_stack(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"expected (N,4,4) poses, got shape {poses.shape}")
    return poses


def format_tum(stamps_ns: np.ndarray, poses: np.ndarray | Trajectory) -> str:
    """TUM text, one 'sec.nanosec tx ty tz qx qy qz qw' line per pose, deterministic.

    `poses` is (N,4,4) transforms, (N,7) rows 'tx ty tz qx qy qz qw', or a Trajectory.
    Values are printed with 9 decimals; quaternions get w >= 0 (not renormalised).
    """
    if isinstance(poses, Trajectory):
        pos, quats = poses.positions, poses.quats_xyzw
    else:
        arr = np.asarray(poses, dtype=float)
        if arr.size == 0:  # nothing tracked: an empty trajectory, not an error
            arr = np.zeros((0, 4, 4))
        if arr.ndim == 2 and arr.shape[1] == 7:
            pos, quats = arr[:, :3], arr[:, 3:]
        else:
            arr = _as_pose_stack(arr)
            pos = arr[:, :3, 3]
            quats = matrices_to_quats(arr[:, :3, :3]) if len(arr) else np.zeros((0, 4))
    stamps = [int(s) for s in np.asarray(stamps_ns).reshape(-1)]
    if len(stamps) != len(pos):
        raise ValueError(f"{len(stamps)} stamps for {len(pos)} poses")
    quats = _canonical_quats(np.asarray(quats, dtype=float))
    lines = []
    for ns, p, q in zip(stamps, pos, quats):
        if ns < 0:
            raise ValueError(f"negative timestamp {ns} ns")
        vals = " ".join(_fmt(v) for v in (*p, *q))
        lines.append(f"{ns // NS_PER_S}.{ns % NS_PER_S:09d} {vals}\n")
    return "".join(lines)


def write_tum(
    path: str | os.PathLike[str], stamps_ns: np.ndarray, poses: np.ndarray | Trajectory
) -> None:
    """Write a TUM trajectory file (see `format_tum`)."""
    Path(path).write_text(format_tum(stamps_ns, poses), encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# Association and alignment


def associate(
    stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt_ns: int = DEFAULT_MAX_DT_NS
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) of nearest stamps within max_dt_ns, one-to-one, sorted by ia.

    Same as evo's nearest-time `associate_trajectories(a, b)`: every stamp of the shorter
    sequence (b when equal) takes its nearest stamp of the other (the earlier one on a tie)
    if within max_dt_ns (inclusive). Unlike evo, a stamp claimed twice is kept only for the
    closer claimant (earlier on a tie), so no pose is used twice.
    """
    a = np.asarray(stamps_a, dtype=np.int64).reshape(-1)
    b = np.asarray(stamps_b, dtype=np.int64).reshape(-1)
    empty = np.zeros(0, dtype=np.intp)
    if a.size == 0 or b.size == 0:
        return empty, empty
    short_is_a = b.size > a.size
    short, long_ = (a, b) if short_is_a else (b, a)
    order = np.argsort(long_, kind="stable")
    srt = long_[order]
    # Nearest neighbour in the sorted long sequence; ties go to the lower stamp.
    hi = np.clip(np.searchsorted(srt, short, side="left"), 0, srt.size - 1)
    lo = np.clip(hi - 1, 0, srt.size - 1)
    d_hi = np.abs(srt[hi] - short)
    d_lo = np.abs(short - srt[lo])
    pick_lo = d_lo <= d_hi
    nearest = np.where(pick_lo, lo, hi)
    dt = np.where(pick_lo, d_lo, d_hi)
    ok = dt <= int(max_dt_ns)
    i_short = np.nonzero(ok)[0]
    i_long = order[nearest[ok]]
    dt = dt[ok]
    # One-to-one: keep, per long index, the claimant with the smallest dt (then smallest index).
    keep_order = np.lexsort((i_short, dt, i_long))
    first = np.ones(keep_order.size, dtype=bool)
    first[1:] = i_long[keep_order][1:] != i_long[keep_order][:-1]
    kept = np.sort(keep_order[first])
    i_short, i_long = i_short[kept], i_long[kept]
    ia, ib = (i_short, i_long) if short_is_a else (i_long, i_short)
    srt_a = np.argsort(ia, kind="stable")
    return ia[srt_a].astype(np.intp), ib[srt_a].astype(np.intp)


def umeyama_se3(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R, t) minimising sum |dst_i - (R src_i + t)|^2 (Umeyama 1991, no scale).

    Raises InputError if the points are degenerate (fewer than 3 or collinear).
    """
    R, t, _ = umeyama(src, dst, with_scale=False)
    return R, t


def umeyama(src: np.ndarray, dst: np.ndarray, *, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, c) minimising sum |dst_i - (c R src_i + t)|^2 (Umeyama 1991; c = 1 without scale), as
    evo's `align(correct_scale=True)` computes it."""
    x = np.asarray(src, dtype=float)
    y = np.asarray(dst, dtype=float)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"expected two (N,3) arrays, got {x.shape} and {y.shape}")
    mx, my = x.mean(axis=0), y.mean(axis=0)
    cov = (y - my).T @ (x - mx) / x.shape[0]
    u, d, vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise InputError(
            f"cannot align trajectories: {x.shape[0]} positions are degenerate "
            "(need at least 3 non-collinear)"
        )
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[2, 2] = -1.0
    R = u @ s @ vt
    c = float(np.trace(np.diag(d) @ s) / np.mean(np.sum(np.square(x - mx), axis=1))) if with_scale else 1.0
    t = my - c * R @ mx
    return R, t, c


def _pairs(est: Trajectory, gt: Trajectory, max_dt_ns: int) -> tuple[Trajectory, Trajectory]:
    if len(est) == 0 or len(gt) == 0:
        raise InputError("cannot evaluate an empty trajectory")
    i_gt, i_est = associate(gt.stamps_ns, est.stamps_ns, max_dt_ns)
    if i_gt.size == 0:
        raise InputError(
            f"no estimate stamp is within {max_dt_ns / 1e6:g} ms of a ground-truth stamp"
        )
    return est.subset(i_est), gt.subset(i_gt)


def _rmse(e: np.ndarray) -> float:
    return math.sqrt(float(np.mean(np.square(e))))


# ---------------------------------------------------------------------------------------------
# Metrics


def ate(est: Trajectory, gt: Trajectory, *, max_dt_ns: int = DEFAULT_MAX_DT_NS,
        correct_scale: bool = False) -> AteResult:
    """Translational ATE after SE(3) Umeyama alignment of the estimate onto the ground truth; with
    `correct_scale`, Sim(3) (`scale`: what the estimate's lengths must be multiplied by)."""
    e, g = _pairs(est, gt, max_dt_ns)
    R, t, c = umeyama(e.positions, g.positions, with_scale=correct_scale)
    aligned = c * e.positions @ R.T + t
    err = np.linalg.norm(g.positions - aligned, axis=1)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = c * R, t
    return AteResult(
        scale=c,
        rmse=_rmse(err),
        mean=float(np.mean(err)),
        median=float(np.median(err)),
        std=float(np.std(err)),
        min=float(np.min(err)),
        max=float(np.max(err)),
        n_pairs=int(err.size),
        alignment=T,
        errors=err,
        stamps_ns=e.stamps_ns.copy(),
    )


def ate_in(est: Trajectory, gt: Trajectory, alignment: np.ndarray, *,
           max_dt_ns: int = DEFAULT_MAX_DT_NS) -> AteResult:
    """Translational ATE under a given alignment (gt ~= alignment @ est), not fitted to `est`: a
    session placed in an earlier session's world, measured there (the earlier one's `ate().alignment`)."""
    e, g = _pairs(est, gt, max_dt_ns)
    err = np.linalg.norm(g.positions - (e.positions @ alignment[:3, :3].T + alignment[:3, 3]), axis=1)
    return AteResult(rmse=_rmse(err), mean=float(np.mean(err)), median=float(np.median(err)), std=float(np.std(err)),
                     min=float(np.min(err)), max=float(np.max(err)), n_pairs=int(err.size),
                     alignment=np.array(alignment, dtype=float), errors=err, stamps_ns=e.stamps_ns.copy())


def rpe(
    est: Trajectory,
    gt: Trajectory,
    *,
    delta: int = 1,
    all_pairs: bool = False,
    max_dt_ns: int = DEFAULT_MAX_DT_NS,
) -> RpeResult:
    """Translational and rotational RPE between associated poses `delta` frames apart.

    Per pair (i, j): E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) with Q ground truth and P estimate;
    errors are |trans(E)| and the angle of rot(E) in degrees. Pairs are (0, d), (d, 2d), ...
    over the associated sequence, or every (i, i+d) with all_pairs (identical for d = 1).
    """
    if int(delta) != delta or delta < 1:
        raise ValueError(f"delta must be a positive integer number of frames, got {delta}")
    delta = int(delta)
    e, g = _pairs(est, gt, max_dt_ns)
    n = len(e)
    if all_pairs:
        i = np.arange(0, max(n - delta, 0))
    else:
        i = np.arange(0, n, delta)[:-1]
    j = i + delta
    if i.size == 0:
        raise InputError(f"RPE needs more than {delta} associated poses, got {n}")
    P, Q = e.matrices(), g.matrices()
    Q_rel = _inv(Q[i]) @ Q[j]
    P_rel = _inv(P[i]) @ P[j]
    E = _inv(Q_rel) @ P_rel
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    from scipy.spatial.transform import Rotation  # imported on use: 0.5 s and ~40 MB
    r_err = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())
    return RpeResult(
        trans_rmse=_rmse(t_err),
        trans_mean=float(np.mean(t_err)),
        trans_median=float(np.median(t_err)),
        trans_max=float(np.max(t_err)),
        rot_rmse_deg=_rmse(r_err),
        rot_mean_deg=float(np.mean(r_err)),
        rot_median_deg=float(np.median(r_err)),
        rot_max_deg=float(np.max(r_err)),
        n_pairs=int(i.size),
        delta=delta,
        trans_errors=t_err,
        rot_errors_deg=r_err,
    )


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a stack of rigid (N,4,4) transforms."""
    Ti = np.tile(np.eye(4), (T.shape[0], 1, 1))
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    Ti[:, :3, :3] = Rt
    Ti[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    return Ti


def format_report(ate_result: AteResult, rpe_result: RpeResult | None = None) -> str:
    """Short human-readable summary, one line per metric."""
    a = ate_result
    lines = [
        f"ATE RMSE {a.rmse * 100:.2f} cm (n={a.n_pairs}; mean {a.mean * 100:.2f}, "
        f"median {a.median * 100:.2f}, std {a.std * 100:.2f}, max {a.max * 100:.2f} cm)"
    ]
    if rpe_result is not None:
        r = rpe_result
        unit = "frame" if r.delta == 1 else f"{r.delta} frames"
        lines.append(
            f"RPE trans RMSE {r.trans_rmse * 100:.2f} cm per {unit} (n={r.n_pairs}; "
            f"mean {r.trans_mean * 100:.2f}, median {r.trans_median * 100:.2f}, "
            f"max {r.trans_max * 100:.2f} cm)"
        )
        lines.append(
            f"RPE rot RMSE {r.rot_rmse_deg:.3f} deg per {unit} (n={r.n_pairs}; "
            f"mean {r.rot_mean_deg:.3f}, median {r.rot_median_deg:.3f}, "
            f"max {r.rot_max_deg:.3f} deg)"
        )
    return "\n".join(lines)
