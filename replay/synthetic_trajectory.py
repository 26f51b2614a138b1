"""The synthetic camera's path: an ellipse around the pillar (one loop in 18 s, 0.3-0.5 m/s, up to
~47 deg/s, 1.2-1.5 m high), looking roughly along its path with a slow look-around; surfaces are
0.5-5 m away (median 2.4-3.6 m). A function of time only, so frame i is the same whatever the
sequence length.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

LOOP_S = 18.0  # one loop around the pillar
TILT_S = 1.0  # a tilted start (`start_tilt_deg`) levels out over this long


def camera_trajectory(t: np.ndarray, *, periodic: bool = False,
                      start_tilt_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (N, 3) and world_from_camera rotations (N, 3, 3) at times t (s).

    `periodic`: the height and look-around periods (7, 7.3, 5.3, 4.1 s) rounded to whole fractions
    of the loop (6, 9, 6, 4.5 s), so the path repeats exactly every LOOP_S: one loop's frames played
    again and again are one smooth, endless session (bench/long_session.py)."""
    t = np.asarray(t, dtype=float)

    def period(p: float) -> float:
        return LOOP_S / max(1, round(LOOP_S / p)) if periodic else p

    w = 2.0 * math.pi / LOOP_S
    th = w * t + math.radians(-100.0)
    ax, ay = 1.3, 0.9
    pos = np.stack(
        [ax * np.cos(th), ay * np.sin(th), 1.35 + 0.15 * np.sin(2.0 * math.pi * t / period(7.0))], axis=1
    )
    heading = np.arctan2(ay * np.cos(th), -ax * np.sin(th))
    yaw = heading + math.radians(30.0) + math.radians(20.0) * np.sin(2.0 * math.pi * t / period(7.3))
    pitch = math.radians(-8.0) + math.radians(7.0) * np.sin(2.0 * math.pi * t / period(5.3) + 1.0)
    if start_tilt_deg:  # looking down by this much at t <= 0, level with the usual path from TILT_S on
        pitch = pitch - math.radians(start_tilt_deg) * 0.5 * (1.0 + np.cos(math.pi * np.clip(t / TILT_S, 0.0, 1.0)))
    roll = math.radians(3.0) * np.sin(2.0 * math.pi * t / period(4.1))
    # body frame: x forward, y left, z up; a positive pitch raises the view.
    body = Rotation.from_euler("ZYX", np.stack([yaw, -pitch, roll], axis=1)).as_matrix()
    optical_in_body = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return pos, body @ optical_in_body
