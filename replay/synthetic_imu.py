"""The synthetic camera's IMU: gyro and accelerometer samples from the path's exact motion, with a
device's white noise and bias random walk (kit/imu.py: ImuNoise), rigidly on the camera (the IMU's
frame is the colour camera's optical frame).

The truth is the trajectory's derivatives (central differences over ±1 ms of an analytic path:
errors ~1e-7 of the signal), gravity along world -z. The noise is a function of the seed and the
sample index only, so sample k is the same whatever the sequence length. For the IMU nobody
calibrated, the noise can be any multiple of the datasheet's, the axes turned and the clock late
(`mismatch`): the consumer is still told the datasheet's noise, the camera's axes and its clock.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from octolog.kit.imu import GRAVITY_MS2, ImuNoise, ImuSamples

DIFF_S = 1e-3  # the central differences' half step
# A consumer MEMS IMU's turn-on biases (BMI055: zero-rate offset up to 1 deg/s, zero-g offset up to
# 70 mg): each axis draws from a normal distribution of this spread.
TURN_ON_GYRO_RADS = np.radians(0.5)
TURN_ON_ACCEL_MS2 = 0.1

Trajectory = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # t -> centres (N, 3), rotations (N, 3, 3)


@dataclass(frozen=True)
class SimulatedImu:
    """The samples, and the biases each one carries (the truth an estimate is checked against)."""

    samples: ImuSamples
    gyro_bias: np.ndarray  # (N, 3) rad/s
    accel_bias: np.ndarray  # (N, 3) m/s²


def true_motion(trajectory: Trajectory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angular velocity (rad/s) and specific force (m/s²) in the camera frame at times t."""
    h = DIFF_S
    p0, r0 = trajectory(t)
    pm, rm = trajectory(t - h)
    pp, rp = trajectory(t + h)
    accel_world = (pp - 2.0 * p0 + pm) / (h * h)
    step = np.einsum("nji,njk->nik", rm, rp)  # R(t-h)^T R(t+h)
    gyro = _log(step) / (2.0 * h)
    up = np.array([0.0, 0.0, GRAVITY_MS2])
    force = np.einsum("nji,nj->ni", r0, accel_world + up)  # R^T (a - g), g = -up
    return gyro, force


def simulate(trajectory: Trajectory, duration_s: float, rate_hz: float, noise: ImuNoise, seed: int,
             start_ns: int, imu_from_camera: np.ndarray | None = None, late_s: float = 0.0) -> SimulatedImu:
    """Samples at k / rate_hz for k = 0 ... up to duration_s (and one sample past it).

    An IMU nobody calibrated: `imu_from_camera` (3x3) turns its axes away from the camera's (which
    the consumer is told they are), and each sample measures the motion `late_s` before its stamp
    (the IMU's clock runs late against the camera's)."""
    n = int(np.floor(duration_s * rate_hz)) + 2
    k = np.arange(n)
    t = k / rate_hz
    gyro, force = true_motion(trajectory, t - late_s)
    if imu_from_camera is not None:
        gyro, force = gyro @ imu_from_camera.T, force @ imu_from_camera.T
    def draws(stream: int, sigma: float) -> np.ndarray:  # one generator per stream: sample k's draw is fixed
        return np.random.default_rng([seed, 0x1A0, stream]).normal(0.0, sigma, (n, 3))

    dt = 1.0 / rate_hz
    turn_on = np.random.default_rng([seed, 0x1A0, 0])
    bg = turn_on.normal(0.0, TURN_ON_GYRO_RADS, 3) + np.cumsum(draws(1, noise.gyro_walk * np.sqrt(dt)), 0)
    ba = turn_on.normal(0.0, TURN_ON_ACCEL_MS2, 3) + np.cumsum(draws(2, noise.accel_walk * np.sqrt(dt)), 0)
    gyro = gyro + bg + draws(3, noise.gyro_noise / np.sqrt(dt))
    force = force + ba + draws(4, noise.accel_noise / np.sqrt(dt))
    stamps = start_ns + np.round(k * (1e9 / rate_hz)).astype(np.int64)
    return SimulatedImu(ImuSamples(stamps, gyro, force), bg, ba)


# `mismatch`'s turn of the IMU's axes: about this fixed oblique axis (every axis of the camera turned)
MISMATCH_AXIS = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)


def mismatch_rotation(degrees: float) -> np.ndarray:
    """imu_from_camera (3x3) of an IMU turned `degrees` about MISMATCH_AXIS (Rodrigues)."""
    a = np.radians(degrees)
    k = MISMATCH_AXIS
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * K @ K


def _log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of (N, 3, 3) rotations (all well under pi here)."""
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) * 0.5, -1.0, 1.0)
    angle = np.arccos(cos)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.sin(angle)
    scale = np.where(s > 1e-12, angle / np.maximum(2.0 * s, 1e-300), 0.5)
    return v * scale[:, None]
