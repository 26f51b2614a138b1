"""The IMU in the SLAM core: the gyro's rotation in the motion model's prediction, the pose through
a visual dropout (INERTIAL), a fit the IMU's motion cannot have made refused, and each placed frame
as evidence for the IMU's estimates (tracker/inertial.py: `Inertial`).

Without samples (a source without an IMU, or `tracker.imu = false`) nothing here changes a pose:
the same bytes as vision alone.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.geometry import invert
from octolog.kit.imu import D455, ImuNoise, ImuSamples
from octolog.tracker.inertial import Inertial, InertialState
from octolog.tracker.keyframe_map import Keyframe
from octolog.tracker.motion import MotionModel

# The gyro's rotation since the last pose, as a prior on the frame's: its sigma per 30 fps frame
# interval (the last pose's own error and the gyro's over one frame, a bias not yet known)
ROTATION_PRIOR_SIGMA = np.radians(0.15)
FRAME_NS = 33_333_333
# A fitted position this far from the IMU's propagated one (plus IMU_GATE_MS per second since vision
# last placed a frame) is a wrong fit: the frame takes the IMU's pose
IMU_GATE_M = 0.05
IMU_GATE_MS = 0.1

RotationPrior = tuple[np.ndarray, float]  # camera_from_world's rotation as the gyro predicts it, sigma (rad)


class ImuFusion:
    """The IMU's part in tracking one camera stream; `motion` is the motion model it predicts from."""

    def __init__(self, motion: MotionModel, *, enabled: bool = True, max_inertial_s: float = 1.5) -> None:
        self._motion = motion
        self.enabled, self.max_inertial_s = enabled, max_inertial_s
        self._imu: Inertial | None = None
        self._camera_from_imu: np.ndarray | None = None  # None: the IMU's axes are the colour camera's
        self._noise: ImuNoise = D455
        # one more residual of the frame's pose fit (tracker/pose.py: optimize_pose)
        self.rotation_prior: RotationPrior | None = None
        self.inertial_frames = 0  # frames given the IMU's pose (INERTIAL)
        self.rejected = 0  # pose fits the IMU's motion could not have made (`rejects`)
        self._remounts = 0  # the IMU's remounts the keyframes' gyro factors have seen (Inertial.remounts)

    def set_camera_from_imu(self, camera_from_imu: np.ndarray) -> None:
        """Where the IMU sits on the colour camera (4x4); before the first samples."""
        self._camera_from_imu = np.asarray(camera_from_imu, np.float64)

    def set_noise(self, noise: ImuNoise) -> None:
        """The IMU's noise (the camera's properties); before the first samples (default: the D455's)."""
        self._noise = noise

    def add(self, samples: ImuSamples) -> None:
        """IMU samples in time order, up to (at least) the next frame's stamp."""
        if not self.enabled or len(samples) == 0:
            return
        if self._imu is None:
            self._imu = Inertial(self._camera_from_imu, self._noise, max_inertial_s=self.max_inertial_s)
        self._imu.add(samples)

    @property
    def inertial(self) -> Inertial | None:
        """The IMU's estimates (None: no samples came)."""
        return self._imu

    @property
    def state(self) -> InertialState | None:
        """What the IMU did (None: no samples came)."""
        return None if self._imu is None else self._imu.state

    @property
    def up(self) -> np.ndarray | None:
        """Up in the world frame as the IMU estimates it (None: not trusted yet, or no IMU)."""
        return None if self._imu is None else self._imu.up

    def predict(self, predicted: np.ndarray, stamp_ns: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The motion model's prediction with the gyro's rotation since the last pose (the
        propagated pose itself after INERTIAL frames), and the IMU's propagated pose (None before
        gravity and velocity are known, or without samples over the interval). A gyro that vision's
        turns contradict (`Inertial.gyro_trusted`: a wrong camera-IMU rotation) leaves the
        constant-velocity prediction and propagates nothing. Sets `rotation_prior` for this frame."""
        self.rotation_prior = None
        motion = self._motion
        if self._imu is None or motion.last_pose is None:
            return predicted, None
        rotation, propagated = self._imu.step_to(stamp_ns)
        if rotation is None or not self._imu.gyro_trusted:  # a gyro vision contradicts predicts nothing
            return predicted, None
        if motion.coasting and propagated is not None:
            out = propagated.copy()
        else:
            out = predicted.copy()
            out[:3, :3] = motion.last_pose[:3, :3] @ rotation
        if (motion.tracked or motion.coasting) and self._imu.gyro_confirmed:  # the step from the last pose is motion
            frames = max(1.0, (stamp_ns - motion.last_stamp) / FRAME_NS)
            self.rotation_prior = (out[:3, :3].T.copy(), ROTATION_PRIOR_SIGMA * np.sqrt(frames))
        return out, propagated

    def rejects(self, camera_from_world: np.ndarray, propagated: np.ndarray | None) -> bool:
        """Whether a fitted pose is further from the IMU's propagated one than the IMU can be wrong
        by (IMU_GATE_M, and IMU_GATE_MS for each second since vision last placed a frame), while
        the IMU is trusted (tracker/inertial.py: Inertial.disagrees)."""
        if propagated is None or self._imu is None:
            return False
        since_s = max(0.0, self._imu.since_visual_s(self._motion.last_stamp))
        moved = float(np.linalg.norm(invert(camera_from_world)[:3, 3] - propagated[:3, 3]))
        if moved <= IMU_GATE_M + IMU_GATE_MS * since_s or not self._imu.disagrees():
            return False
        self.rejected += 1
        return True

    def coasts(self, propagated: np.ndarray | None) -> bool:
        """Whether a frame vision could not place takes the IMU's `propagated` pose (INERTIAL)."""
        if propagated is None or self._imu is None or not self._imu.coast():
            return False
        self.inertial_frames += 1
        return True

    def keyframe_rotation(self, kf_id: int, stamp_ns: int, keyframes: list[Keyframe]
                          ) -> tuple[int, np.ndarray, float] | None:
        """A keyframe at this frame: the gyro's rotation since the keyframe before (Keyframe.gyro).
        While vision contradicts the gyro, the factors it gave leave every keyframe."""
        if self._imu is None:
            return None
        if not self._imu.gyro_trusted or self._imu.remounts != self._remounts:  # or taken through a wrong rotation
            self._remounts = self._imu.remounts
            for kf in keyframes:
                kf.gyro = None
        return self._imu.keyframe_rotation(kf_id, stamp_ns)

    def observe(self, stamp_ns: int, pose: np.ndarray, *, continuous: bool, moved: np.ndarray | None = None) -> None:
        """A frame vision placed at `pose`; `moved`: the correction the map took at it (the IMU's
        recent poses move with it)."""
        self._motion.coasting = False
        if self._imu is None:
            return
        if moved is not None:
            self._imu.rebase(moved)
        self._imu.observe(stamp_ns, pose, continuous=continuous)
