"""The IMU's samples as the tracker's intake takes them off the bus (`camera/gyro/sample`,
`camera/accel/sample`, sensor_msgs/Imu), handed to the tracker with the frame they came before.

The reader thread `offer`s every IMU sample as it comes and `mark`s each frame with how many it had
by then; the tracking thread `take`s, for the frame it tracks, the samples up to that frame's mark:
in the order the bus delivered them, so a replay gives the same samples to the same frame. The
gyro's samples carry the accelerometer's linearly interpolated at their stamps (kit/imu.py: unite).
"""

from __future__ import annotations

import threading

import numpy as np

from octolog.kit.bus import Received
from octolog.kit.imu import ImuSamples, unite
from octolog.schemas import codec
from octolog.schemas.topics import ACCEL, GYRO

IMU_TOPICS = (GYRO, ACCEL)


class ImuIntake:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._gyro: list[tuple[int, float, float, float]] = []
        self._accel: list[tuple[int, float, float, float]] = []
        self._taken = (0, 0)
        self.frame_id = ""  # the IMU's frame, from its first sample

    def offer(self, r: Received) -> bool:
        """Keep `r` if it is an IMU sample (True); anything else is not for here (False)."""
        if r.topic not in IMU_TOPICS:
            return False
        msg = r.decode()
        v = msg.angular_velocity if r.topic == GYRO else msg.linear_acceleration
        with self._lock:
            (self._gyro if r.topic == GYRO else self._accel).append((codec.stamp_ns(msg.header), v.x, v.y, v.z))
            self.frame_id = self.frame_id or msg.header.frame_id
        return True

    def mark(self) -> tuple[int, int]:
        with self._lock:
            return len(self._gyro), len(self._accel)

    def take(self, mark: tuple[int, int]) -> ImuSamples:
        """The gyro samples since the last take up to `mark`, with the accelerometer's at their stamps."""
        with self._lock:
            g0, a0 = self._taken
            gyro = self._gyro[g0:mark[0]]
            accel = self._accel[max(0, a0 - 1):mark[1]]  # the one before: to interpolate across the frames
            self._taken = (max(g0, mark[0]), max(a0, mark[1]))
        if not gyro or not accel:
            return ImuSamples.empty()
        g, a = np.array(gyro), np.array(accel)
        g_ns = np.array([row[0] for row in gyro], np.int64)
        a_ns = np.array([row[0] for row in accel], np.int64)
        return unite(g_ns, g[:, 1:], a_ns, a[:, 1:])
