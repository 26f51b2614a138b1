"""The tracker's IMU: preintegration between frames, the gyro's bias, gravity, velocity and the
accelerometer's bias, estimated online from the visual poses, and the pose through a visual dropout.

- Preintegration is gtsam's `PreintegratedImuMeasurements` (Forster et al.'s on-manifold
  preintegration); its `predict` re-applies a changed bias to first order, which also gives the
  bias Jacobians below (by differences, with no re-integration).
- The gyro's bias: each tracked frame adds the rotation over the last `GYRO_SPAN` frames, the
  visual one against the gyro's, to running normal equations (forgetting over `GYRO_MEMORY_S`);
  the bias is their solution, rotation prediction uses it from the first frames on.
- Gravity, the velocity and the accelerometer's bias: a linear least-squares alignment over the
  newest `WINDOW_S` of tracked frames (nodes every `NODE_STEP` frames): the preintegrated velocity
  and position changes against the visual positions, which RGB-D gives in metres, so no scale and
  no special motion is needed (at rest the accelerometer alone says where gravity is; the bias
  has a prior). Gravity's magnitude is held at 9.81 m/s².
- The state (pose, velocity) is propagated frame to frame; a frame vision cannot place is given
  the propagated pose (INERTIAL) for up to `max_inertial_s`, and tracking resumes from it.

All in the tracker's world frame (the first keyframe's camera frame); the IMU's frame is placed on
the camera by `camera_from_imu`. Deterministic: the same samples and poses give the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from octolog.kit.imu import D455, GRAVITY_MS2, ImuNoise, ImuSamples
from octolog.tracker.pose import so3_log

GYRO_SPAN = 6  # frames each gyro-bias rotation spans (200 ms at 30 fps)
GYRO_MEMORY_S = 30.0  # the gyro-bias estimate forgets older rotations over this long (bias drift)
VISUAL_ROTATION_SIGMA = 3e-4  # rad: a tracked frame's rotation error
VISUAL_POSITION_SIGMA = 4e-3  # m: a tracked frame's position error
MAX_ROTATION_RESIDUAL = np.radians(2.0)  # a span the gyro disagrees with more is not evidence (a bad pose)
# a span turning faster is no evidence for the gyro's bias: its images are blurred, vision's
# rotations uncertain
MAX_EVIDENCE_RATE = np.radians(60.0)
WINDOW_S = 2.0  # gravity, velocity and accelerometer-bias alignment: the newest tracked time
NODE_STEP = 5  # frames between the alignment's nodes
INIT_S = 1.0  # tracked time before the alignment is trusted
REALIGN_EVERY = 10  # tracked frames between alignments
ACCEL_BIAS_SIGMA = 0.1  # m/s²: the accelerometer bias's prior spread (a consumer MEMS part)
GYRO_BIAS_SIGMA = np.radians(1.0)  # rad/s: the gyro bias's prior spread
# The IMU is trusted (it may place a frame, and veto vision's fit) once its propagated position has
# been within AGREE_M of vision's for TRUST_FRAMES frames in a row; vision overrules it after
# MAX_DISAGREEING vetoes in a row
AGREE_M = 0.02
# Vision checks the gyro: over the newest GYRO_CHECK_SPANS spans of GYRO_CHECK_FRAMES frames turning
# at least GYRO_CHECK_MIN_RAD, the median of vision's rotation against the gyro's, relative to the
# angle turned, must be at most GYRO_AGREE_RATIO. A camera-IMU rotation off by some 15 degrees or
# more fails (its residual is that angle's share of every turn), as do swapped axes and a made-up
# IMU; vision's own rotation over two frames of a heavily blurred first turn erred by up to 0.2.
# A gyro that fails predicts nothing (the motion model's constant velocity), and the gyro is a prior
# of the pose fit and a back-end factor only once at least one span has passed (`gyro_confirmed`)
GYRO_CHECK_SPANS = 15
GYRO_CHECK_FRAMES = 2  # frames each checked span covers: the first check two frames in
GYRO_CHECK_MIN_RAD = np.radians(1.0)  # a span turning less says little about the axes
GYRO_AGREE_RATIO = 0.25
TRUST_FRAMES = 30
MAX_DISAGREEING = 3
MAX_GAP_NS = 100_000_000  # an IMU silent this long between samples leaves the interval unmeasured
# A gyro's rotation is off by this fraction of the angle turned (the path's, there and back): its
# scale-factor and cross-axis errors (BMI055: about 1 % each), a camera-IMU rotation known to a
# fraction of a degree, and the discrete integration of a fast-changing rate
GYRO_SCALE_ERROR = 0.01
_EPS_BIAS = 1e-4


@dataclass
class _Record:
    stamp_ns: int
    world_from_imu: np.ndarray  # (4, 4)
    visual: bool  # placed by vision (else propagated: INERTIAL)
    continuous: bool  # the step from the record before it is motion (not a relocalisation)
    segments: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # dt, gyro, accel since the record before


@dataclass
class InertialState:
    """What the summary reports of the IMU."""

    samples: int = 0
    initialised_at_ns: int = -1
    gyro_bias: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    accel_bias: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    gravity: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    distrusted: int = 0  # times vision overruled the IMU (MAX_DISAGREEING vetoes in a row)
    trusted_frames: int = 0  # frames the IMU's pose was trusted at (Inertial.trusted)


class Inertial:
    """One camera's IMU in the tracker: `add` samples as they come, `step_to` at each frame (the
    rotation and pose it predicts), then `observe` the frame's visual pose or `coast` through it."""

    def __init__(self, camera_from_imu: np.ndarray | None = None, noise: ImuNoise = D455,
                 max_inertial_s: float = 1.5) -> None:
        self.camera_from_imu = np.eye(4) if camera_from_imu is None else np.asarray(camera_from_imu, float)
        self.imu_from_camera = np.linalg.inv(self.camera_from_imu)
        self.noise, self.max_inertial_s = noise, max_inertial_s
        p = gtsam.PreintegrationParams(np.zeros(3))
        p.setGyroscopeCovariance(np.eye(3) * noise.gyro_noise**2)
        p.setAccelerometerCovariance(np.eye(3) * noise.accel_noise**2)
        p.setIntegrationCovariance(np.eye(3) * 1e-8)
        self._params = p
        self._t = np.zeros(0, np.int64)
        self._w = np.zeros((0, 3))
        self._a = np.zeros((0, 3))
        self.bg, self.ba = np.zeros(3), np.zeros(3)
        self.gravity: np.ndarray | None = None  # world frame, once aligned
        self._H, self._g = np.eye(3) / GYRO_BIAS_SIGMA**2, np.zeros(3)
        self._records: list[_Record] = []
        self._velocity: np.ndarray | None = None  # world, at the newest record
        self._since_align = 0
        self._pending: tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray] | None] | None = None
        self._propagated: tuple[int, np.ndarray, np.ndarray] | None = None  # stamp, world_from_imu, velocity
        self._agreeing = self._disagreeing = 0
        self._rot_residuals: list[float] = []  # the newest turning spans' residuals over the angle turned
        self._keyframe_mark: tuple[int, int] | None = None  # the newest keyframe's id and stamp
        self._up_sum, self._up_n = np.zeros(3), 0  # the trusted alignments' up directions
        self.state = InertialState()

    # -- samples --------------------------------------------------------------------------------

    def add(self, samples: ImuSamples) -> None:
        """Samples in time order (older than the newest held: ignored)."""
        if len(samples) == 0:
            return
        keep = samples.stamp_ns > (self._t[-1] if self._t.size else np.iinfo(np.int64).min)
        self._t = np.concatenate([self._t, samples.stamp_ns[keep]])
        self._w = np.concatenate([self._w, samples.gyro[keep]])
        self._a = np.concatenate([self._a, samples.accel[keep]])
        self.state.samples += int(keep.sum())

    def _segments(self, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Pieces (dt s, gyro, accel) covering [t0, t1] between consecutive samples, each with the
        samples' values interpolated at its middle (as ORB-SLAM3 averages consecutive samples: holding
        a sample until the next lags a changing rate by half a sample period, a 0.06 deg error over a
        keyframe interval of a fast turn); None where the IMU does not cover the interval."""
        t = self._t
        if t.size == 0 or t1 <= t0 or t[0] > t0 or t[-1] < t1 - MAX_GAP_NS:
            return None
        lo = int(np.searchsorted(t, t0, side="right")) - 1
        hi = int(np.searchsorted(t, t1, side="left"))
        edges = np.concatenate([[t0], t[lo + 1:hi], [t1]])
        if np.diff(edges).max() > MAX_GAP_NS:
            return None
        mid = (edges[:-1] + edges[1:]) // 2
        tk = t[lo:hi + 1] - t0  # the samples around the interval, as small numbers
        w = np.stack([np.interp(mid - t0, tk, self._w[lo:hi + 1, k]) for k in range(3)], axis=1)
        a = np.stack([np.interp(mid - t0, tk, self._a[lo:hi + 1, k]) for k in range(3)], axis=1)
        return np.diff(edges) * 1e-9, w, a

    def _preintegrate(self, segments: tuple[np.ndarray, np.ndarray, np.ndarray]) -> gtsam.PreintegratedImuMeasurements:
        pim = gtsam.PreintegratedImuMeasurements(self._params, gtsam.imuBias.ConstantBias(self.ba, self.bg))
        for dt, w, a in zip(*segments):
            if dt > 0:
                pim.integrateMeasurement(a, w, float(dt))
        return pim

    @staticmethod
    def _delta(pim: gtsam.PreintegratedImuMeasurements, ba: np.ndarray, bg: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ΔR, Δp, Δv) of an interval for biases (ba, bg), first order about its integration's."""
        s = pim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(ba, bg))
        return s.attitude().matrix(), np.asarray(s.position()), np.asarray(s.velocity())

    # -- per frame ------------------------------------------------------------------------------

    def step_to(self, stamp_ns: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """For the frame at `stamp_ns`, after the newest record: the camera's rotation over the
        interval (camera_prev_from_camera, 3x3; None without IMU data) and, once aligned, the
        propagated world_from_camera (None before). Call `observe` or `coast` after."""
        self._pending = self._propagated = None
        if not self._records:
            return None, None
        last = self._records[-1]
        seg = self._segments(last.stamp_ns, stamp_ns)
        self._pending = (stamp_ns, seg)
        if seg is None:
            return None, None
        pim = self._preintegrate(seg)
        dR, dp, dv = self._delta(pim, self.ba, self.bg)
        Rci = self.camera_from_imu[:3, :3]
        rotation = Rci @ dR @ Rci.T
        if self.gravity is None or self._velocity is None or not self._can_coast(stamp_ns):
            return rotation, None
        R, p = last.world_from_imu[:3, :3], last.world_from_imu[:3, 3]
        dt = float(seg[0].sum())
        T = np.eye(4)
        T[:3, :3] = R @ dR
        T[:3, 3] = p + self._velocity * dt + 0.5 * self.gravity * dt * dt + R @ dp
        self._propagated = (stamp_ns, T, self._velocity + self.gravity * dt + R @ dv)
        self.state.trusted_frames += self.trusted
        return rotation, (T @ self.imu_from_camera if self.trusted else None)

    @property
    def up(self) -> np.ndarray | None:
        """Up (unit, against gravity) in the world frame: the mean direction of the alignments made
        while the IMU was trusted (each from WINDOW_S of motion, its accelerometer bias confounded
        with gravity differently as the camera turns); None before the first."""
        if self._up_n == 0:
            return None
        return self._up_sum / np.linalg.norm(self._up_sum)

    @property
    def gyro_trusted(self) -> bool:
        """Vision does not contradict the gyro's rotations: the median relative residual of the
        newest GYRO_CHECK_SPANS turning spans is at most GYRO_AGREE_RATIO (true before the first
        span; a wrong camera-IMU rotation, swapped axes or a made-up IMU fail at it)."""
        return not self._rot_residuals or float(np.median(self._rot_residuals)) <= GYRO_AGREE_RATIO

    @property
    def gyro_confirmed(self) -> bool:
        """Vision's turns have confirmed the gyro's rotations (`gyro_trusted` after the first
        turning span): what the pose fit's prior and the back end's factors wait for."""
        return bool(self._rot_residuals) and self.gyro_trusted

    @property
    def trusted(self) -> bool:
        """The IMU's propagated poses have agreed with vision's for the last TRUST_FRAMES frames it
        placed (a wrong extrinsic, clock offset or noise model never gets there)."""
        return self._agreeing >= TRUST_FRAMES

    def disagrees(self) -> bool:
        """Vision placed this frame where the IMU says it cannot be: True while the IMU is trusted
        and this has not gone on for MAX_DISAGREEING frames (then vision wins, the IMU must earn
        trust again)."""
        self._disagreeing += 1
        if self._disagreeing > MAX_DISAGREEING:
            self._agreeing = 0
            self.state.distrusted += 1
            return False
        return self.trusted

    def since_visual_s(self, stamp_ns: int) -> float:
        """Seconds from the newest frame vision placed to `stamp_ns` (inf: none)."""
        last_visual = next((r.stamp_ns for r in reversed(self._records) if r.visual), None)
        return float("inf") if last_visual is None else (stamp_ns - last_visual) * 1e-9

    def _can_coast(self, stamp_ns: int) -> bool:
        return self.since_visual_s(stamp_ns) <= self.max_inertial_s

    def coast(self) -> bool:
        """The frame `step_to` propagated to takes the propagated pose (INERTIAL); False if there is none."""
        # step_to propagated to this frame only with gravity, a velocity and time left to coast
        if self._pending is None or self._propagated is None or not self.trusted:
            return False
        stamp_ns, seg = self._pending
        _, T, v = self._propagated
        self._records.append(_Record(stamp_ns, T, False, True, seg))
        self._velocity = v
        self._pending = None
        return True

    def observe(self, stamp_ns: int, world_from_camera: np.ndarray, *, continuous: bool = True) -> None:
        """The frame's visual pose (after `step_to`): evidence for the biases, the velocity and gravity."""
        seg = self._pending[1] if self._pending is not None and self._pending[0] == stamp_ns else None
        self._pending = None
        T = world_from_camera @ self.camera_from_imu
        if self._propagated is not None and self._propagated[0] == stamp_ns and continuous:
            off = float(np.linalg.norm(T[:3, 3] - self._propagated[1][:3, 3]))
            self._agreeing = self._agreeing + 1 if off <= AGREE_M else 0
        self._propagated = None
        self._disagreeing = 0
        if seg is not None and continuous and self._velocity is not None and self.gravity is not None:
            pim = self._preintegrate(seg)
            R = self._records[-1].world_from_imu[:3, :3]
            _, _, dv = self._delta(pim, self.ba, self.bg)
            self._velocity = self._velocity + self.gravity * float(seg[0].sum()) + R @ dv
        elif not continuous or seg is None:
            self._velocity = None
        self._records.append(_Record(stamp_ns, T, True, continuous and seg is not None, seg))
        self._gyro_check()
        self._gyro_evidence()
        self._since_align += 1
        if self._since_align >= REALIGN_EVERY or (self.gravity is None or self._velocity is None):
            self._align()
        self._trim()

    def keyframe_rotation(self, kf_id: int, stamp_ns: int) -> tuple[int, np.ndarray, float] | None:
        """A keyframe at the frame `step_to` went to (or the first frame): the gyro's rotation since
        the keyframe before (its id, camera_before_from_camera, sigma in rad) for the back end's
        bundle adjustment; None without IMU over every interval since, or before vision has
        confirmed the gyro (`gyro_confirmed`)."""
        prev, self._keyframe_mark = self._keyframe_mark, (kf_id, stamp_ns)
        pending = self._pending
        if prev is None or pending is None or pending[0] != stamp_ns or pending[1] is None or not self.gyro_confirmed:
            return None
        since = [r for r in self._records if r.stamp_ns > prev[1]]
        if not any(r.stamp_ns == prev[1] for r in self._records) or \
                not all(r.continuous and r.segments is not None for r in since):
            return None
        seg = _joined([r.segments for r in since] + [pending[1]])  # type: ignore[list-item]
        dR, _, _ = self._delta(self._preintegrate(seg), self.ba, self.bg)
        dt = float(seg[0].sum())
        bias_sigma = float(np.sqrt(np.linalg.eigvalsh(np.linalg.inv(self._H)).max()))
        turned = float(np.linalg.norm(seg[1] - self.bg, axis=1) @ seg[0])  # the path's angle, not the net
        sigma = np.sqrt(self.noise.gyro_noise**2 * dt + (bias_sigma * dt) ** 2 + (GYRO_SCALE_ERROR * turned) ** 2)
        Rci = self.camera_from_imu[:3, :3]
        return prev[0], Rci @ dR @ Rci.T, float(sigma)

    def rebase(self, correction: np.ndarray) -> None:
        """The map moved (a back-end correction, 4x4 world_new_from_world_old): so do the recent poses."""
        for r in self._records:
            r.world_from_imu = correction @ r.world_from_imu
        if self._velocity is not None:
            self._velocity = correction[:3, :3] @ self._velocity

    # -- estimation -----------------------------------------------------------------------------

    def _chain(self, n: int) -> list[_Record] | None:
        """The newest n+1 records if they are one unbroken chain of visual frames with IMU between."""
        recs = self._records[-(n + 1):]
        if len(recs) < n + 1 or not all(r.visual for r in recs) or \
                not all(r.continuous and r.segments is not None for r in recs[1:]):
            return None
        return recs

    def _span_segments(self, recs: list[_Record]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _joined([r.segments for r in recs[1:]])  # type: ignore[misc]

    def _span(self, n: int) -> tuple[gtsam.PreintegratedImuMeasurements, float, np.ndarray, np.ndarray] | None:
        """Over the newest n frames (an unbroken visual chain): the preintegration, its seconds, and
        the rotation the gyro and vision each give (imu_first_from_imu_last); None without one."""
        recs = self._chain(n)
        if recs is None:
            return None
        seg = self._span_segments(recs)
        pim = self._preintegrate(seg)
        R0, _, _ = self._delta(pim, self.ba, self.bg)
        return pim, float(seg[0].sum()), R0, recs[0].world_from_imu[:3, :3].T @ recs[-1].world_from_imu[:3, :3]

    def _gyro_check(self) -> None:
        """The rotation over the newest GYRO_CHECK_FRAMES frames, vision's against the gyro's,
        relative to the angle turned, into the check of `gyro_trusted` (a span turning less than
        GYRO_CHECK_MIN_RAD is no evidence)."""
        span = self._span(GYRO_CHECK_FRAMES)
        if span is None:
            return
        _, _, R0, vis = span
        turned = max(float(np.linalg.norm(so3_log(R0))), float(np.linalg.norm(so3_log(vis))))
        if turned >= GYRO_CHECK_MIN_RAD:
            residual = float(np.linalg.norm(so3_log(R0.T @ vis))) / turned
            self._rot_residuals = [*self._rot_residuals[-GYRO_CHECK_SPANS + 1:], residual]

    def _gyro_evidence(self) -> None:
        """The rotation over the newest GYRO_SPAN frames into the gyro bias's normal equations."""
        span = self._span(GYRO_SPAN)
        if span is None:
            return
        pim, dt, R0, vis = span
        r = so3_log(R0.T @ vis)
        if np.linalg.norm(r) > MAX_ROTATION_RESIDUAL or np.linalg.norm(so3_log(R0)) > MAX_EVIDENCE_RATE * dt:
            return
        J = np.zeros((3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = _EPS_BIAS
            Rk, _, _ = self._delta(pim, self.ba, self.bg + e)
            J[:, k] = so3_log(R0.T @ Rk) / _EPS_BIAS  # d rotation / d bias
        # r(b) ~ r(bg) - J (b - bg): J b ~ r + J bg
        sigma2 = 2 * VISUAL_ROTATION_SIGMA**2 + self.noise.gyro_noise**2 * dt
        forget = np.exp(-dt / GYRO_SPAN / GYRO_MEMORY_S)
        prior = np.eye(3) / GYRO_BIAS_SIGMA**2
        self._H = prior + forget * (self._H - prior) + J.T @ J / sigma2
        self._g = forget * self._g + J.T @ (r + J @ self.bg) / sigma2
        self.bg = np.linalg.solve(self._H, self._g)
        self.state.gyro_bias = self.bg.tolist()

    def _align(self) -> None:
        """Gravity, the nodes' velocities and the accelerometer bias from the newest WINDOW_S."""
        recs = self._newest_chain()
        if recs is None or (recs[-1].stamp_ns - recs[0].stamp_ns) * 1e-9 < INIT_S:
            return
        nodes = recs[::-1][::NODE_STEP][::-1]  # ends at the newest
        idx = [recs.index(n) for n in nodes]
        n = len(nodes)
        rows, rhs, w = [], [], []
        cols = 3 * n + 6  # velocities, gravity, accel bias change
        for k in range(n - 1):
            a, b = nodes[k], nodes[k + 1]
            seg = self._span_segments(recs[idx[k]:idx[k + 1] + 1])
            pim = self._preintegrate(seg)
            dt = float(seg[0].sum())
            _, dp, dv = self._delta(pim, self.ba, self.bg)
            Jp, Jv = np.zeros((3, 3)), np.zeros((3, 3))
            for j in range(3):
                e = np.zeros(3)
                e[j] = _EPS_BIAS
                _, dpj, dvj = self._delta(pim, self.ba + e, self.bg)
                Jp[:, j], Jv[:, j] = (dpj - dp) / _EPS_BIAS, (dvj - dv) / _EPS_BIAS
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
            sigma_v = self.noise.accel_noise * np.sqrt(dt) + 1e-3
            rows.append(A), rhs.append(Ri @ dv), w.append(np.full(3, 1.0 / sigma_v))
        A = np.zeros((3, cols))
        A[:, 3 * n + 3:] = np.eye(3)
        rows.append(A), rhs.append(np.zeros(3)), w.append(np.full(3, 1.0 / ACCEL_BIAS_SIGMA))
        A, y, wt = np.vstack(rows), np.concatenate(rhs), np.concatenate(w)
        x = np.linalg.lstsq(A * wt[:, None], y * wt, rcond=None)[0]
        g = x[3 * n:3 * n + 3]
        if not 0.5 * GRAVITY_MS2 < np.linalg.norm(g) < 1.5 * GRAVITY_MS2:
            return  # the window does not explain the accelerometer: wait for a better one
        g = g / np.linalg.norm(g) * GRAVITY_MS2
        # again with gravity's magnitude held: velocities and the bias change
        keep = np.r_[0:3 * n, 3 * n + 3:cols]
        x2 = np.linalg.lstsq(A[:, keep] * wt[:, None], (y - A[:, 3 * n:3 * n + 3] @ g) * wt, rcond=None)[0]
        self.gravity = g
        if self.trusted:
            self._up_sum, self._up_n = self._up_sum - g / GRAVITY_MS2, self._up_n + 1
        self.ba = self.ba + x2[3 * n:]
        self._velocity = x2[3 * (n - 1):3 * n].copy()
        self._since_align = 0
        if self.state.initialised_at_ns < 0:
            self.state.initialised_at_ns = recs[-1].stamp_ns
        self.state.accel_bias, self.state.gravity = self.ba.tolist(), g.tolist()

    def _newest_chain(self) -> list[_Record] | None:
        """The newest visual records over WINDOW_S, back to the first break in the chain of motion."""
        newest = self._records[-1].stamp_ns
        out: list[_Record] = []
        for r in reversed(self._records):
            if not r.visual or (newest - r.stamp_ns) * 1e-9 > WINDOW_S:
                break
            out.append(r)
            if not r.continuous or r.segments is None:
                break  # it starts the chain
        out.reverse()
        return out if len(out) > NODE_STEP else None

    def _trim(self) -> None:
        """Keep the records and samples the estimates still need."""
        newest = self._records[-1].stamp_ns
        keep_from = newest - int((WINDOW_S + 1.0) * 1e9)
        while len(self._records) > GYRO_SPAN + 1 and self._records[0].stamp_ns < keep_from:
            self._records.pop(0)
        cut = int(np.searchsorted(self._t, newest, side="left")) - 1
        if cut > 0:
            self._t, self._w, self._a = self._t[cut:], self._w[cut:], self._a[cut:]


def _joined(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Consecutive intervals' pieces (dt, gyro, accel) as one interval's."""
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))  # type: ignore[return-value]
