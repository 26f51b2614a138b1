"""The synthetic camera's path: an ellipse around the pillar (one loop in 18 s, 0.3-0.5 m/s, up to
~47 deg/s, 1.2-1.5 m high), looking roughly along its path with a slow look-around; surfaces are
0.5-5 m away (median 2.4-3.6 m). A function of time only, so frame i is the same whatever the
sequence length.

`path_start_s` starts the walk that far along it, `reverse` walks it the other way round (still
looking towards the pillar): a later walk through the same room from another place and in
the other direction (bench/localize.py).

`motion="turns"` is the hand-held user turning to look at the room: the same walk, and on top of
it a turn of the head every 1.5 s, 0.75 s long, by +85, -85, -70, +70 degrees of yaw in turn
(a smooth start and stop) with a 10-degree nod (pitch) on each: with the walk's own turning, the
camera turns at 150-210 deg/s at the peak of each turn.
"""

from __future__ import annotations

import math

import numpy as np

from octolog.kit.geometry import euler_to_matrices

LOOP_S = 18.0  # one loop around the pillar
TILT_S = 1.0  # a tilted start (`start_tilt_deg`) levels out over this long
MOTIONS = ("loop", "turns")
TURN_S, TURN_EVERY_S = 0.75, 1.5  # `turns`: each turn takes TURN_S, one starts every TURN_EVERY_S
TURN_YAW_DEG = (85.0, -85.0, -70.0, 70.0)  # the turns' yaw, in turn (the yaw is back to 0 after four)
TURN_PITCH_DEG = (10.0, -10.0, -10.0, 10.0)


def _turns(t: np.ndarray, steps_deg: tuple[float, ...]) -> np.ndarray:
    """The angle (rad) a head turning by `steps_deg` in turn has turned at times t: each step a
    raised-cosine ramp over TURN_S (peak rate pi/2 * step / TURN_S), one every TURN_EVERY_S."""
    k = np.floor(t / TURN_EVERY_S).astype(np.int64)
    within = np.clip((t - k * TURN_EVERY_S) / TURN_S, 0.0, 1.0)
    steps = np.radians(np.asarray(steps_deg))
    done = np.concatenate([[0.0], np.cumsum(steps)])  # after 0, 1, 2, ... whole steps (mod len)
    n = len(steps)
    before = (k // n) * done[-1] + done[k % n]
    return before + steps[k % n] * 0.5 * (1.0 - np.cos(math.pi * within))


def camera_trajectory(t: np.ndarray, *, periodic: bool = False, start_tilt_deg: float = 0.0,
                      motion: str = "loop", path_start_s: float = 0.0,
                      reverse: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (N, 3) and world_from_camera rotations (N, 3, 3) at times t (s).

    `periodic`: the height and look-around periods (7, 7.3, 5.3, 4.1 s) rounded to whole fractions
    of the loop (6, 9, 6, 4.5 s), so the path repeats exactly every LOOP_S: one loop's frames played
    again and again are one smooth, endless session (bench/long_session.py)."""
    t = np.asarray(t, dtype=float)

    def period(p: float) -> float:
        return LOOP_S / max(1, round(LOOP_S / p)) if periodic else p

    w = 2.0 * math.pi / LOOP_S
    s = path_start_s + (-t if reverse else t)  # how far along the walk (s of the forward walk)
    th = w * s + math.radians(-100.0)
    ax, ay = 1.3, 0.9
    pos = np.stack(
        [ax * np.cos(th), ay * np.sin(th), 1.35 + 0.15 * np.sin(2.0 * math.pi * s / period(7.0))], axis=1
    )
    heading = np.arctan2(ay * np.cos(th), -ax * np.sin(th)) + (math.pi if reverse else 0.0)
    inward = math.radians(-30.0 if reverse else 30.0)  # the pillar is to the left going forward, right going back
    yaw = heading + inward + math.radians(20.0) * np.sin(2.0 * math.pi * s / period(7.3))
    pitch = math.radians(-8.0) + math.radians(7.0) * np.sin(2.0 * math.pi * s / period(5.3) + 1.0)
    if start_tilt_deg:  # looking down by this much at t <= 0, level with the usual path from TILT_S on
        pitch = pitch - math.radians(start_tilt_deg) * 0.5 * (1.0 + np.cos(math.pi * np.clip(t / TILT_S, 0.0, 1.0)))
    if motion == "turns":
        yaw = yaw + _turns(np.maximum(t, 0.0), TURN_YAW_DEG)
        pitch = pitch + _turns(np.maximum(t, 0.0), TURN_PITCH_DEG)
    elif motion != "loop":
        raise ValueError(f"motion {motion!r}: want one of {', '.join(MOTIONS)}")
    roll = math.radians(3.0) * np.sin(2.0 * math.pi * s / period(4.1))
    # body frame: x forward, y left, z up; a positive pitch raises the view.
    body = euler_to_matrices("ZYX", np.stack([yaw, -pitch, roll], axis=1))
    optical_in_body = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return pos, body @ optical_in_body
