"""Gravity, the velocity and the accelerometer's bias, from the IMU against vision's positions.

A linear least-squares alignment over the newest `WINDOW_S` of placed frames (nodes every
`NODE_STEP` frames): the preintegrated velocity and position changes against the visual positions,
which RGB-D gives in metres, so no scale and no special motion is needed (at rest the accelerometer
alone says where gravity is; the bias has a prior). Gravity's magnitude is held at 9.81 m/s².
Between alignments the velocity is propagated frame to frame.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.imu import GRAVITY_MS2, ImuNoise
from octolog.tracker.preintegration import (
    EPS_BIAS,
    FrameHistory,
    Preintegrator,
    Segments,
    bias_corrected,
    chain_segments,
)

VISUAL_POSITION_SIGMA = 4e-3  # m: a tracked frame's position error
WINDOW_S = 2.0  # gravity, velocity and accelerometer-bias alignment: the newest tracked time
NODE_STEP = 5  # frames between the alignment's nodes
INIT_S = 1.0  # tracked time before the alignment is trusted
REALIGN_EVERY = 10  # tracked frames between alignments
ACCEL_BIAS_SIGMA = 0.1  # m/s²: the accelerometer bias's prior spread (a consumer MEMS part)


class GravityAlignment:
    """Gravity (world frame), the IMU's velocity at the newest frame, the accelerometer's bias, and
    up averaged over the alignments made while the IMU was trusted."""

    def __init__(self, preintegrator: Preintegrator, noise: ImuNoise) -> None:
        self._preintegrator = preintegrator
        self._accel_noise = noise.accel_noise
        self.ba = np.zeros(3)
        self.gravity: np.ndarray | None = None  # world frame, once aligned
        self.velocity: np.ndarray | None = None  # world, at the newest frame
        self._since_align = 0
        self._up_sum, self._up_n = np.zeros(3), 0  # the trusted alignments' up directions

    def set_noise(self, noise: ImuNoise) -> None:
        """The accelerometer's white noise from here on (a measured one in place of the datasheet's)."""
        self._accel_noise = noise.accel_noise

    @property
    def known(self) -> bool:
        """Gravity and the velocity are known: a pose can be propagated."""
        return self.gravity is not None and self.velocity is not None

    @property
    def up(self) -> np.ndarray | None:
        """Up (unit, against gravity): the mean direction of the alignments made while the IMU was
        trusted; None before the first."""
        if self._up_n == 0:
            return None
        return self._up_sum / np.linalg.norm(self._up_sum)

    # -- between alignments ---------------------------------------------------------------------

    def propagate(self, world_from_imu: np.ndarray, dt: float, dR: np.ndarray, dp: np.ndarray, dv: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray] | None:
        """The pose (world_from_imu, 4x4) and velocity `dt` s after the newest frame at
        `world_from_imu`, from the interval's preintegrated (ΔR, Δp, Δv); None before gravity and
        the velocity are known."""
        if self.gravity is None or self.velocity is None:
            return None
        R, p = world_from_imu[:3, :3], world_from_imu[:3, 3]
        T = np.eye(4)
        T[:3, :3] = R @ dR
        T[:3, 3] = p + self.velocity * dt + 0.5 * self.gravity * dt * dt + R @ dp
        return T, self.velocity + self.gravity * dt + R @ dv

    def advance(self, segments: Segments, world_from_imu_rotation: np.ndarray, bg: np.ndarray) -> None:
        """The velocity through one more interval from the frame at `world_from_imu_rotation` (3x3),
        preintegrated with the gyro's bias `bg`; while `known`."""
        pim = self._preintegrator.integrate(segments, self.ba, bg)
        _, _, dv = bias_corrected(pim, self.ba, bg)
        R = world_from_imu_rotation
        self.velocity = self.velocity + self.gravity * float(segments[0].sum()) + R @ dv  # type: ignore[operator]

    def take_velocity(self, velocity: np.ndarray | None) -> None:
        """The velocity at the newest frame as someone else knows it (a propagated one; None: lost)."""
        self.velocity = velocity

    def rebase(self, rotation: np.ndarray) -> None:
        """The map turned by `rotation` (3x3, world_new_from_world_old): so does the velocity."""
        if self.velocity is not None:
            self.velocity = rotation @ self.velocity

    # -- alignment ------------------------------------------------------------------------------

    def count_frame(self) -> None:
        """One more placed frame since the last alignment."""
        self._since_align += 1

    @property
    def due(self) -> bool:
        """REALIGN_EVERY frames have passed, or gravity or the velocity is not known."""
        return self._since_align >= REALIGN_EVERY or (self.gravity is None or self.velocity is None)

    def align(self, history: FrameHistory, bg: np.ndarray, trusted: bool) -> bool:
        """Gravity, the nodes' velocities and the accelerometer bias from the newest WINDOW_S of
        `history` (its newest record placed by vision), with the gyro's bias `bg`; `trusted`: the
        IMU's poses are (the direction counts towards `up`). False: no window yet, or one that
        does not explain the accelerometer."""
        recs = history.newest_chain(WINDOW_S)
        if len(recs) <= NODE_STEP or (recs[-1].stamp_ns - recs[0].stamp_ns) * 1e-9 < INIT_S:
            return False
        nodes = recs[::-1][::NODE_STEP][::-1]  # ends at the newest
        idx = [recs.index(n) for n in nodes]
        n = len(nodes)
        rows, rhs, w = [], [], []
        cols = 3 * n + 6  # velocities, gravity, accel bias change
        for k in range(n - 1):
            a, b = nodes[k], nodes[k + 1]
            seg = chain_segments(recs[idx[k]:idx[k + 1] + 1])
            pim = self._preintegrator.integrate(seg, self.ba, bg)
            dt = float(seg[0].sum())
            _, dp, dv = bias_corrected(pim, self.ba, bg)
            Jp, Jv = np.zeros((3, 3)), np.zeros((3, 3))
            for j in range(3):
                e = np.zeros(3)
                e[j] = EPS_BIAS
                _, dpj, dvj = bias_corrected(pim, self.ba + e, bg)
                Jp[:, j], Jv[:, j] = (dpj - dp) / EPS_BIAS, (dvj - dv) / EPS_BIAS
            Ri, pi, pj = a.world_from_imu[:3, :3], a.world_from_imu[:3, 3], b.world_from_imu[:3, 3]
            # p_j - p_i - R_i dp = v_i dt + g dt²/2 + R_i Jp δba
            A = np.zeros((3, cols))
            A[:, 3 * k:3 * k + 3] = np.eye(3) * dt
            A[:, 3 * n:3 * n + 3] = np.eye(3) * 0.5 * dt * dt
            A[:, 3 * n + 3:] = Ri @ Jp
            rows.append(A), rhs.append(pj - pi - Ri @ dp), w.append(np.full(3, 1.0 / (np.sqrt(2) * VISUAL_POSITION_SIGMA)))
            # v_j - v_i - g dt - R_i Jv δba = R_i dv
            A = np.zeros((3, cols))
            A[:, 3 * k + 3:3 * k + 6] = np.eye(3)
            A[:, 3 * k:3 * k + 3] -= np.eye(3)
            A[:, 3 * n:3 * n + 3] = -np.eye(3) * dt
            A[:, 3 * n + 3:] = -Ri @ Jv
            sigma_v = self._accel_noise * np.sqrt(dt) + 1e-3
            rows.append(A), rhs.append(Ri @ dv), w.append(np.full(3, 1.0 / sigma_v))
        A = np.zeros((3, cols))
        A[:, 3 * n + 3:] = np.eye(3)
        rows.append(A), rhs.append(np.zeros(3)), w.append(np.full(3, 1.0 / ACCEL_BIAS_SIGMA))
        A, y, wt = np.vstack(rows), np.concatenate(rhs), np.concatenate(w)
        x = np.linalg.lstsq(A * wt[:, None], y * wt, rcond=None)[0]
        g = x[3 * n:3 * n + 3]
        if not 0.5 * GRAVITY_MS2 < np.linalg.norm(g) < 1.5 * GRAVITY_MS2:
            return False  # the window does not explain the accelerometer: wait for a better one
        g = g / np.linalg.norm(g) * GRAVITY_MS2
        # again with gravity's magnitude held: velocities and the bias change
        keep = np.r_[0:3 * n, 3 * n + 3:cols]
        x2 = np.linalg.lstsq(A[:, keep] * wt[:, None], (y - A[:, 3 * n:3 * n + 3] @ g) * wt, rcond=None)[0]
        self.gravity = g
        if trusted:
            self._up_sum, self._up_n = self._up_sum - g / GRAVITY_MS2, self._up_n + 1
        self.ba = self.ba + x2[3 * n:]
        self.velocity = x2[3 * (n - 1):3 * n].copy()
        self._since_align = 0
        return True
