"""The tracker's IMU: the pose and rotation it predicts at each frame, its trust against vision,
and the parts it is composed of, each owning its state:

- `tracker/preintegration.py`: the samples (`ImuBuffer`), their preintegration between frames
  (`Preintegrator`, gtsam's `PreintegratedImuMeasurements`) and the newest frames with the IMU
  between them (`FrameHistory`);
- `tracker/gyro.py`: vision's check of the gyro's rotations (`GyroCheck`) and the gyro's bias
  (`GyroBias`);
- `tracker/gravity_alignment.py`: gravity, the velocity and the accelerometer's bias
  (`GravityAlignment`);
- here: whether the IMU's propagated poses are trusted (`ImuTrust`), and `Inertial`, which composes
  them. The state (pose, velocity) is propagated frame to frame; a frame vision cannot place is
  given the propagated pose (INERTIAL) for up to `max_inertial_s`, and tracking resumes from it.

All in the tracker's world frame (the first keyframe's camera frame); the IMU's frame is placed on
the camera by `camera_from_imu`. Deterministic: the same samples and poses give the same bytes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from octolog.kit.imu import D455, ImuNoise, ImuSamples
from octolog.tracker.gravity_alignment import WINDOW_S, GravityAlignment
from octolog.tracker.imu_mounting import ImuMounting
from octolog.tracker.imu_noise import NoiseMeter
from octolog.tracker.gyro import GYRO_CHECK_FRAMES, GYRO_SPAN, GyroBias, GyroCheck, GyroSpan
from octolog.tracker.pose import so3_log
from octolog.tracker.preintegration import (
    FrameHistory,
    FrameRecord,
    ImuBuffer,
    Preintegrator,
    Segments,
    bias_corrected,
    chain_segments,
    joined,
)

# The IMU is trusted (it may place a frame, and veto vision's fit) once its propagated position has
# been within AGREE_M of vision's at every frame for TRUST_S, and at least TRUST_FRAMES frames, in a
# row: time, not a frame count, so a camera at 15 fps or a live stream that skips frames earns it as
# soon (a wrong extrinsic, clock offset or noise model is metres off within a few frames). Vision
# overrules it after MAX_DISAGREEING vetoes in a row.
AGREE_M = 0.02
TRUST_S = 0.5
TRUST_FRAMES = 10
MAX_DISAGREEING = 3
REMOUNT_DEG = 0.5  # a camera-IMU rotation moved further makes the gyro's earlier rotations wrong
MEASURE_EVERY_S = 1.0  # the IMU's noise is measured again after this long of frames


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
    # the IMU's noise (kit/imu.py: ImuNoise's four figures): the datasheet's (or the calibration
    # file's) the tracker started from, and the one measured from the samples (empty: too few)
    noise_assumed: list[float] = field(default_factory=list)
    noise_measured: list[float] = field(default_factory=list)
    # the IMU on the camera as measured (4x4 camera_from_imu; empty: the turns have not shown it
    # yet), its rotation's angle from the stated one, and how late the IMU's clock runs (ms)
    camera_from_imu: list[list[float]] = field(default_factory=list)
    rotation_change_deg: float = 0.0
    late_ms: float = 0.0


class ImuTrust:
    """Whether the IMU's propagated poses are trusted: the run of frames they agreed with vision's
    at, and the run of vetoes vision's fits have taken from it."""

    def __init__(self) -> None:
        self._agreeing = self._disagreeing = 0
        self._since_ns = self._last_ns = 0  # the run of agreeing frames: its first and newest stamp
        self.distrusted = 0  # times vision overruled the IMU

    @property
    def trusted(self) -> bool:
        """The propagated poses agreed with vision's at every frame for the last TRUST_S (and at
        least TRUST_FRAMES frames)."""
        return self._agreeing >= TRUST_FRAMES and self._last_ns - self._since_ns >= TRUST_S * 1e9

    def compare(self, off_m: float, stamp_ns: int) -> None:
        """Vision placed the frame at `stamp_ns` `off_m` from the propagated position."""
        if off_m > AGREE_M:
            self._agreeing = 0
            return
        if self._agreeing == 0:
            self._since_ns = stamp_ns
        self._agreeing += 1
        self._last_ns = stamp_ns

    def placed(self) -> None:
        """Vision placed a frame: the run of vetoes ends."""
        self._disagreeing = 0

    def disagrees(self) -> bool:
        """One more veto: True while trusted and not for more than MAX_DISAGREEING frames in a row
        (then vision wins, and trust must be earned again)."""
        self._disagreeing += 1
        if self._disagreeing > MAX_DISAGREEING:
            self._agreeing = 0
            self.distrusted += 1
            return False
        return self.trusted


class Inertial:
    """One camera's IMU in the tracker: `add` samples as they come, `step_to` at each frame (the
    rotation and pose it predicts), then `observe` the frame's visual pose or `coast` through it."""

    def __init__(self, camera_from_imu: np.ndarray | None = None, noise: ImuNoise = D455,
                 max_inertial_s: float = 1.5) -> None:
        self.camera_from_imu = np.eye(4) if camera_from_imu is None else np.asarray(camera_from_imu, float)
        self.imu_from_camera = np.linalg.inv(self.camera_from_imu)
        self.noise, self.max_inertial_s = noise, max_inertial_s
        self._buffer = ImuBuffer()
        self._preintegrator = Preintegrator(noise)
        self._history = FrameHistory()
        self._gyro_check = GyroCheck()
        self._gyro_bias = GyroBias(noise)
        self._alignment = GravityAlignment(self._preintegrator, noise)
        self._trust = ImuTrust()
        self._meter = NoiseMeter(noise)
        self._mounting = ImuMounting(self.camera_from_imu)
        self._spans = 0  # spans of GYRO_SPAN frames read so far
        self.remounts = 0  # times the camera-IMU rotation moved by more than REMOUNT_DEG
        self._next_measure_ns: int | None = None  # the stamp from which the noise is measured again
        self._pending: tuple[int, Segments | None] | None = None  # the frame step_to went to, its pieces
        self._propagated: tuple[int, np.ndarray, np.ndarray] | None = None  # stamp, world_from_imu, velocity
        self._keyframe_mark: tuple[int, int] | None = None  # the newest keyframe's id and stamp
        self.state = InertialState(noise_assumed=list(dataclasses.astuple(noise)))

    @property
    def bg(self) -> np.ndarray:
        """The gyro's bias (rad/s)."""
        return self._gyro_bias.bg

    @property
    def ba(self) -> np.ndarray:
        """The accelerometer's bias (m/s²)."""
        return self._alignment.ba

    @property
    def gravity(self) -> np.ndarray | None:
        """Gravity in the world frame, once aligned."""
        return self._alignment.gravity

    def add(self, samples: ImuSamples) -> None:
        """Samples in time order (older than the newest held: ignored)."""
        self.state.samples += self._buffer.add(samples)
        self._meter.add(samples)

    # -- per frame ------------------------------------------------------------------------------

    def step_to(self, stamp_ns: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """For the frame at `stamp_ns`, after the newest record: the camera's rotation over the
        interval (camera_prev_from_camera, 3x3; None without IMU data) and, once aligned, the
        propagated world_from_camera (None before). Call `observe` or `coast` after."""
        self._pending = self._propagated = None
        last = self._history.last
        if last is None:
            return None, None
        seg = self._buffer.segments(last.stamp_ns, stamp_ns)
        self._pending = (stamp_ns, seg)
        if seg is None:
            return None, None
        ba, bg = self._alignment.ba, self._gyro_bias.bg
        dR, dp, dv = bias_corrected(self._preintegrator.integrate(seg, ba, bg), ba, bg)
        Rci = self.camera_from_imu[:3, :3]
        rotation = Rci @ dR @ Rci.T
        if not self._can_coast(stamp_ns):
            return rotation, None
        propagated = self._alignment.propagate(last.world_from_imu, float(seg[0].sum()), dR, dp, dv)
        if propagated is None:
            return rotation, None
        T, v = propagated
        self._propagated = (stamp_ns, T, v)
        self.state.trusted_frames += self.trusted
        return rotation, (T @ self.imu_from_camera if self.trusted else None)

    @property
    def up(self) -> np.ndarray | None:
        """Up (unit, against gravity) in the world frame: the mean direction of the alignments made
        while the IMU was trusted (each from WINDOW_S of motion, its accelerometer bias confounded
        with gravity differently as the camera turns); None before the first."""
        return self._alignment.up

    @property
    def gyro_trusted(self) -> bool:
        """Vision does not contradict the gyro's rotations: the median relative residual of the
        newest GYRO_CHECK_SPANS turning spans is at most GYRO_AGREE_RATIO (true before the first
        span; a wrong camera-IMU rotation, swapped axes or a made-up IMU fail at it)."""
        return self._gyro_check.trusted

    @property
    def gyro_confirmed(self) -> bool:
        """Vision's turns have confirmed the gyro's rotations (`gyro_trusted` after the first
        turning span): what the pose fit's prior and the back end's factors wait for."""
        return self._gyro_check.confirmed

    @property
    def trusted(self) -> bool:
        """The IMU's propagated poses have agreed with vision's for the last TRUST_S of frames it
        placed (a wrong extrinsic, clock offset or noise model never gets there)."""
        return self._trust.trusted

    def disagrees(self) -> bool:
        """Vision placed this frame where the IMU says it cannot be: True while the IMU is trusted
        and this has not gone on for MAX_DISAGREEING frames (then vision wins, the IMU must earn
        trust again)."""
        out = self._trust.disagrees()
        self.state.distrusted = self._trust.distrusted
        return out

    def since_visual_s(self, stamp_ns: int) -> float:
        """Seconds from the newest frame vision placed to `stamp_ns` (inf: none)."""
        return self._history.since_visual_s(stamp_ns)

    def _can_coast(self, stamp_ns: int) -> bool:
        return self.since_visual_s(stamp_ns) <= self.max_inertial_s

    def coast(self) -> bool:
        """The frame `step_to` propagated to takes the propagated pose (INERTIAL); False if there is none."""
        # step_to propagated to this frame only with gravity, a velocity and time left to coast
        if self._pending is None or self._propagated is None or not self.trusted:
            return False
        stamp_ns, seg = self._pending
        _, T, v = self._propagated
        self._history.append(FrameRecord(stamp_ns, T, False, True, seg))
        self._alignment.take_velocity(v)
        self._pending = None
        return True

    def observe(self, stamp_ns: int, world_from_camera: np.ndarray, *, continuous: bool = True) -> None:
        """The frame's visual pose (after `step_to`): evidence for the biases, the velocity and gravity."""
        seg = self._pending[1] if self._pending is not None and self._pending[0] == stamp_ns else None
        self._pending = None
        T = world_from_camera @ self.camera_from_imu
        if self._propagated is not None and self._propagated[0] == stamp_ns and continuous:
            self._trust.compare(float(np.linalg.norm(T[:3, 3] - self._propagated[1][:3, 3])), stamp_ns)
        self._propagated = None
        self._trust.placed()
        last = self._history.last
        if seg is not None and continuous and self._alignment.known and last is not None:
            self._alignment.advance(seg, last.world_from_imu[:3, :3], self._gyro_bias.bg)
        elif not continuous or seg is None:
            self._alignment.take_velocity(None)
        self._history.append(FrameRecord(stamp_ns, T, True, continuous and seg is not None, seg))
        self._check_gyro()
        self._estimate_gyro_bias()
        self._measure(stamp_ns)
        self._alignment.count_frame()
        if self._alignment.due:
            self._align(stamp_ns)
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
        since = self._history.segments_since(prev[1])
        if since is None:
            return None
        seg = joined([*since, pending[1]])
        ba, bg = self._alignment.ba, self._gyro_bias.bg
        dR, _, _ = bias_corrected(self._preintegrator.integrate(seg, ba, bg), ba, bg)
        sigma = self._gyro_bias.rotation_sigma(seg)
        Rci = self.camera_from_imu[:3, :3]
        return prev[0], Rci @ dR @ Rci.T, sigma

    def rebase(self, correction: np.ndarray) -> None:
        """The map moved (a back-end correction, 4x4 world_new_from_world_old): so do the recent poses."""
        self._history.rebase(correction)
        self._alignment.rebase(correction[:3, :3])

    # -- the parts' evidence ---------------------------------------------------------------------

    def _span(self, n: int) -> GyroSpan | None:
        """Over the newest n frames (an unbroken visual chain): the preintegration, its seconds, and
        the rotation the gyro and vision each give (imu_first_from_imu_last); None without one."""
        recs = self._history.chain(n)
        if recs is None:
            return None
        seg = chain_segments(recs)
        ba, bg = self._alignment.ba, self._gyro_bias.bg
        pim = self._preintegrator.integrate(seg, ba, bg)
        R0, _, _ = bias_corrected(pim, ba, bg)
        vision = recs[0].world_from_imu[:3, :3].T @ recs[-1].world_from_imu[:3, :3]
        return GyroSpan(pim, float(seg[0].sum()), R0, vision, seg[1][-1] - seg[1][0])

    def _check_gyro(self) -> None:
        span = self._span(GYRO_CHECK_FRAMES)
        if span is not None:
            self._gyro_check.add(span)

    def _estimate_gyro_bias(self) -> None:
        span = self._span(GYRO_SPAN)
        if span is None:
            return
        self._spans += 1
        if self._spans % GYRO_SPAN == 0:  # spans that do not overlap: independent rows, an honest covariance
            self._mounting.add(span.gyro, span.vision, span.rate_change, span.seconds, self._gyro_bias.bg)
        if self._gyro_bias.add(span, self._alignment.ba):
            self.state.gyro_bias = self._gyro_bias.bg.tolist()

    def _align(self, stamp_ns: int) -> None:
        if not self._alignment.align(self._history, self._gyro_bias.bg, self.trusted):
            return
        if self.state.initialised_at_ns < 0:
            self.state.initialised_at_ns = stamp_ns
        self.state.accel_bias = self._alignment.ba.tolist()
        self.state.gravity = self._alignment.gravity.tolist()  # type: ignore[union-attr]

    def _measure(self, stamp_ns: int) -> None:
        """Every MEASURE_EVERY_S of frames: the noise measured from the samples up to this frame
        (tracker/imu_noise.py) takes the datasheet's place in every part that weighs the IMU, and
        the camera-IMU rotation and clock offset measured from vision's turns
        (tracker/imu_mounting.py) the calibration's."""
        if self._next_measure_ns is not None and stamp_ns < self._next_measure_ns:
            return
        self._next_measure_ns = stamp_ns + int(MEASURE_EVERY_S * 1e9)
        noise = self._meter.measure(stamp_ns)
        if noise is not None:
            self.noise = noise
            self._preintegrator.set_noise(noise)
            self._gyro_bias.set_noise(noise)
            self._alignment.set_noise(noise)
            self.state.noise_measured = list(dataclasses.astuple(noise))
        rotation = self._mounting.solve_rotation()
        if rotation is not None:
            self._remount(rotation)
        late = self._mounting.solve_late()
        if late is not None:
            self._buffer.retime(round(late * 1e9) - self._buffer.late_ns)
            self._mounting.late_s = self._buffer.late_ns * 1e-9
            self.state.late_ms = self._mounting.late_s * 1e3

    def _remount(self, rotation: np.ndarray) -> None:
        """The IMU's rotation on the camera is `rotation` (camera_from_imu's 3x3). Moved by more than
        REMOUNT_DEG, the gyro's rotations taken with the old one are wrong: the back end's factors
        from them go (`remounts`), and the gyro's bias starts again from the one estimated along."""
        change = float(np.degrees(np.linalg.norm(so3_log(self._mounting.rotation.T @ rotation))))
        if change > REMOUNT_DEG:
            self.remounts += 1
            self._gyro_bias.restart(self._mounting.solve_bias())
        new = self.camera_from_imu.copy()
        new[:3, :3] = rotation
        self._history.remount(self.imu_from_camera @ new)
        self.camera_from_imu, self.imu_from_camera = new, np.linalg.inv(new)
        self._mounting.rotation = rotation.copy()
        self.state.camera_from_imu = new.tolist()
        self.state.rotation_change_deg = self._mounting.rotation_change_deg

    def _trim(self) -> None:
        """Keep the records and samples the estimates still need."""
        newest = self._history.last.stamp_ns  # type: ignore[union-attr]
        self._history.trim(newest - int((WINDOW_S + 1.0) * 1e9), GYRO_SPAN + 1)
        self._buffer.trim(newest)
