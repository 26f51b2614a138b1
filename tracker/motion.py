"""The tracker's motion model: the constant-velocity prediction from the last poses, and with an IMU
the gyro's rotation in it, the pose through a visual dropout (INERTIAL) and each placed frame as
evidence for the IMU's estimates (tracker/inertial.py).

A mixin of `RgbdSlam` (tracker.odometry), which owns the pose and motion state these methods read
and set. Without samples (a source without an IMU, or `tracker.imu = false`) nothing here runs: the
same bytes as vision alone.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.geometry import RgbdFrame, invert
from octolog.kit.imu import D455, ImuNoise, ImuSamples
from octolog.tracker.inertial import Inertial, InertialState
from octolog.tracker.interface import TrackingState, TrackResult
from octolog.tracker.pose import so3_exp, so3_log

# The motion model extrapolates at most this many frame intervals: a long gap is a stall.
MAX_PREDICTION_STEPS = 4.0
# The gyro's rotation since the last pose, as a prior on the frame's: its sigma per 30 fps frame
# interval (the last pose's own error and the gyro's over one frame, a bias not yet known)
ROTATION_PRIOR_SIGMA = np.radians(0.15)
FRAME_NS = 33_333_333
# A fitted position this far from the IMU's propagated one (plus IMU_GATE_MS per second since vision
# last placed a frame) is a wrong fit: the frame takes the IMU's pose
IMU_GATE_M = 0.05
IMU_GATE_MS = 0.1


class MotionModel:
    """Prediction, and IMU fusion, for `RgbdSlam`."""

    _imu: Inertial | None = None
    _camera_from_imu: np.ndarray | None = None  # None: the IMU's axes are the colour camera's
    _imu_noise: ImuNoise = D455
    _coasting = False  # the last pose came from the IMU
    # camera_from_world's rotation as the gyro predicts it from the last pose, and its sigma (rad):
    # one more residual of the frame's pose fit (tracker/pose.py: optimize_pose)
    _rotation_prior: tuple[np.ndarray, float] | None = None
    inertial_frames = 0  # frames given the IMU's pose (INERTIAL)
    imu_rejected = 0  # pose fits the IMU's motion could not have made (_imu_rejects)

    # -- motion model ---------------------------------------------------------------------------

    def _predict(self, stamp_ns: int) -> np.ndarray:
        """Constant-velocity prediction of world_from_camera from the last tracked frame, scaled to
        the interval since it (at most MAX_PREDICTION_STEPS frames: a LOST stretch keeps that pose
        instead of spinning on with the velocity it had)."""
        assert self._last_pose is not None
        if self._velocity is None:
            return self._last_pose.copy()
        rotvec, trans, dt_ns = self._velocity
        dt_new = stamp_ns - self._last_stamp
        s = dt_new / dt_ns if dt_ns > 0 and dt_new > 0 else 1.0
        s = min(s, MAX_PREDICTION_STEPS)
        step = np.eye(4)
        step[:3, :3] = so3_exp(rotvec * s)
        step[:3, 3] = trans * s
        return self._last_pose @ step

    def _remember(self, stamp_ns: int, pose: np.ndarray, *, continuous: bool = True) -> None:
        """Keep a tracked frame's pose, and the velocity from the last tracked one (over any short
        LOST gap); found again, the velocity is unknown. A LOST frame changes neither."""
        if continuous and self._last_pose is not None:
            step = invert(self._last_pose) @ pose
            self._velocity = (so3_log(step[:3, :3]), step[:3, 3].copy(), stamp_ns - self._last_stamp)
        else:
            self._velocity = None
        self._last_pose = pose.copy()
        self._last_stamp = stamp_ns
        self._last_ok = True

    def set_camera_from_imu(self, camera_from_imu: np.ndarray) -> None:
        """Where the IMU sits on the colour camera (4x4); before the first samples."""
        self._camera_from_imu = np.asarray(camera_from_imu, np.float64)

    def set_imu_noise(self, noise: ImuNoise) -> None:
        """The IMU's noise (the camera's properties); before the first samples (default: the D455's)."""
        self._imu_noise = noise

    def add_imu(self, samples: ImuSamples) -> None:
        """IMU samples in time order, up to (at least) the next frame's stamp."""
        if not self.params.imu or len(samples) == 0:
            return
        if self._imu is None:
            self._imu = Inertial(self._camera_from_imu, self._imu_noise, max_inertial_s=self.params.max_inertial_s)
        self._imu.add(samples)

    @property
    def imu_state(self) -> InertialState | None:
        """What the IMU did (None: no samples came)."""
        return None if self._imu is None else self._imu.state

    @property
    def imu_up(self) -> np.ndarray | None:
        """Up in the world frame as the IMU estimates it (None: not trusted yet, or no IMU)."""
        return None if self._imu is None else self._imu.up

    def _imu_predict(self, predicted: np.ndarray, stamp_ns: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The motion model's prediction with the gyro's rotation since the last pose (the
        propagated pose itself after INERTIAL frames), and the IMU's propagated pose (None before
        gravity and velocity are known, or without samples over the interval). A gyro that vision's
        turns contradict (`Inertial.gyro_trusted`: a wrong camera-IMU rotation) leaves the
        constant-velocity prediction and propagates nothing."""
        self._rotation_prior = None
        if self._imu is None or self._last_pose is None:
            return predicted, None
        rotation, propagated = self._imu.step_to(stamp_ns)
        if rotation is None or not self._imu.gyro_trusted:  # a gyro vision contradicts predicts nothing
            return predicted, None
        if self._coasting and propagated is not None:
            out = propagated.copy()
        else:
            out = predicted.copy()
            out[:3, :3] = self._last_pose[:3, :3] @ rotation
        if (self._last_ok or self._coasting) and self._imu.gyro_confirmed:  # the step from the last pose is motion
            frames = max(1.0, (stamp_ns - self._last_stamp) / FRAME_NS)
            self._rotation_prior = (out[:3, :3].T.copy(), ROTATION_PRIOR_SIGMA * np.sqrt(frames))
        return out, propagated

    def _imu_rejects(self, camera_from_world: np.ndarray, propagated: np.ndarray | None) -> bool:
        """Whether a fitted pose is further from the IMU's propagated one than the IMU can be wrong
        by (IMU_GATE_M, and IMU_GATE_MS for each second since vision last placed a frame), while
        the IMU is trusted (tracker/inertial.py: Inertial.disagrees)."""
        if propagated is None or self._imu is None:
            return False
        since_s = max(0.0, self._imu.since_visual_s(self._last_stamp))
        moved = float(np.linalg.norm(invert(camera_from_world)[:3, 3] - propagated[:3, 3]))
        if moved <= IMU_GATE_M + IMU_GATE_MS * since_s or not self._imu.disagrees():
            return False
        self.imu_rejected += 1
        return True

    def _imu_coast(self, frame: RgbdFrame, propagated: np.ndarray | None) -> TrackResult | None:
        """The frame vision could not place, with the IMU's pose (INERTIAL); None if the IMU has none."""
        if propagated is None or self._imu is None or not self._imu.coast():
            return None
        assert self._last_pose is not None
        self.inertial_frames += 1
        ref = self._keyframes[-1]
        self._frames.append((frame.stamp_ns, ref.id, invert(ref.world_from_camera) @ propagated))
        step = invert(self._last_pose) @ propagated
        self._velocity = (so3_log(step[:3, :3]), step[:3, 3].copy(), frame.stamp_ns - self._last_stamp)
        self._last_pose, self._last_stamp = propagated.copy(), frame.stamp_ns
        self._last_ok, self._coasting = False, True
        self._last_inlier_ids = np.zeros(0, np.int64)
        return TrackResult(frame.seq, frame.stamp_ns, propagated.copy(), TrackingState.INERTIAL, False, -1, 0, 0,
                           depth_inverse_offset=self.depth_offset)

    def _imu_keyframe(self, kf_id: int, stamp_ns: int) -> tuple[int, np.ndarray, float] | None:
        """A keyframe at this frame: the gyro's rotation since the keyframe before (Keyframe.gyro).
        While vision contradicts the gyro, the factors it gave leave every keyframe."""
        if self._imu is None:
            return None
        if not self._imu.gyro_trusted:
            for kf in self._keyframes:
                kf.gyro = None
        return self._imu.keyframe_rotation(kf_id, stamp_ns)

    def _imu_observe(self, stamp_ns: int, pose: np.ndarray, *, continuous: bool,
                     moved: np.ndarray | None = None) -> None:
        """A frame vision placed at `pose`; `moved`: the correction the map took at it (the IMU's
        recent poses move with it)."""
        self._coasting = False
        if self._imu is None:
            return
        if moved is not None:
            self._imu.rebase(moved)
        self._imu.observe(stamp_ns, pose, continuous=continuous)
