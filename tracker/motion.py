"""The tracker's motion model: the last tracked pose, the velocity from the one before, and the
constant-velocity prediction of the next frame's pose from them.

`MotionModel` owns that state; the other parts of the SLAM core (tracker/slam.py) read it and move
it only through its methods (a back-end correction, a depth-scale correction, an IMU pose).
"""

from __future__ import annotations

import numpy as np

from octolog.kit.geometry import invert
from octolog.tracker.pose import so3_exp, so3_log

# The motion model extrapolates at most this many frame intervals: a long gap is a stall.
MAX_PREDICTION_STEPS = 4.0

Velocity = tuple[np.ndarray, np.ndarray, int]  # rotation vector, translation, over dt_ns


class MotionModel:
    """The camera's last pose and velocity; `predict` the next pose, `remember` a tracked one."""

    def __init__(self) -> None:
        self.last_pose: np.ndarray | None = None  # world_from_camera of the last placed frame
        self.last_stamp = 0
        self.tracked = False  # the last frame was placed by vision (ORB-SLAM's "tracking OK")
        self.coasting = False  # the last pose came from the IMU (INERTIAL)
        self.velocity: Velocity | None = None

    def predict(self, stamp_ns: int) -> np.ndarray:
        """Constant-velocity prediction of world_from_camera from the last tracked frame, scaled to
        the interval since it (at most MAX_PREDICTION_STEPS frames: a LOST stretch keeps that pose
        instead of spinning on with the velocity it had)."""
        assert self.last_pose is not None
        if self.velocity is None:
            return self.last_pose.copy()
        rotvec, trans, dt_ns = self.velocity
        dt_new = stamp_ns - self.last_stamp
        s = dt_new / dt_ns if dt_ns > 0 and dt_new > 0 else 1.0
        s = min(s, MAX_PREDICTION_STEPS)
        step = np.eye(4)
        step[:3, :3] = so3_exp(rotvec * s)
        step[:3, 3] = trans * s
        return self.last_pose @ step

    def continuous(self, stamp_ns: int) -> bool:
        """Whether the prediction for a frame at `stamp_ns` is meaningful, so its pose is judged as a
        step from it: after a tracked frame, or a few LOST frames after one."""
        return self.tracked or self.coasting or (
            self.velocity is not None and stamp_ns - self.last_stamp <= MAX_PREDICTION_STEPS * self.velocity[2])

    def remember(self, stamp_ns: int, pose: np.ndarray, *, continuous: bool = True) -> None:
        """Keep a tracked frame's pose, and the velocity from the last tracked one (over any short
        LOST gap); found again, the velocity is unknown. A LOST frame changes neither."""
        if continuous and self.last_pose is not None:
            step = invert(self.last_pose) @ pose
            self.velocity = (so3_log(step[:3, :3]), step[:3, 3].copy(), stamp_ns - self.last_stamp)
        else:
            self.velocity = None
        self.last_pose = pose.copy()
        self.last_stamp = stamp_ns
        self.tracked = True

    def coast(self, stamp_ns: int, pose: np.ndarray) -> None:
        """A frame placed by the IMU alone: its pose, and the velocity to it; not tracked."""
        assert self.last_pose is not None
        step = invert(self.last_pose) @ pose
        self.velocity = (so3_log(step[:3, :3]), step[:3, 3].copy(), stamp_ns - self.last_stamp)
        self.last_pose, self.last_stamp = pose.copy(), stamp_ns
        self.tracked, self.coasting = False, True

    def lost(self) -> None:
        """A frame nobody placed: the next prediction still comes from the last placed frame."""
        self.tracked = self.coasting = False

    def move(self, delta: np.ndarray) -> None:
        """The map moved under the camera by `delta` (a back-end correction): the last pose with it."""
        if self.last_pose is not None:
            self.last_pose = delta @ self.last_pose

    def scale(self, s: float) -> None:
        """The map's translations scaled by `s` (a depth-scale correction): the pose and velocity with them."""
        if self.last_pose is not None:
            self.last_pose = scaled(self.last_pose, s)
        if self.velocity is not None:
            rotvec, trans, dt = self.velocity
            self.velocity = (rotvec, trans * s, dt)

    def take(self, other: MotionModel) -> None:
        """Another model's pose and velocity (a map of its own becomes the map); the IMU's coasting stays."""
        self.last_pose, self.last_stamp, self.tracked, self.velocity = (
            other.last_pose, other.last_stamp, other.tracked, other.velocity)


def scaled(T: np.ndarray, s: float) -> np.ndarray:
    """`T` with its translation scaled by `s`."""
    out = T.copy()
    out[:3, 3] *= s
    return out
