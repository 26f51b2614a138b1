"""IMU samples as octolog carries them: stamps, gyro (rad/s) and accelerometer (m/s²) readings in the
IMU's own frame, a noise model per device, and the TUM-layout `imu.txt` reader.

A D455 sends its gyro and its accelerometer as two streams at their own rates
(`camera/gyro/sample`, `camera/accel/sample`, sensor_msgs/Imu each); `unite` puts them on the gyro's
stamps, the accelerometer linearly interpolated (librealsense's `unite_imu_method=linear`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octolog.kit.errors import InputError

GRAVITY_MS2 = 9.80665  # standard gravity; the magnitude the tracker holds its gravity estimate to


@dataclass(frozen=True)
class ImuNoise:
    """An IMU's continuous-time noise: white noise densities and bias random walks (Kalibr's names)."""

    gyro_noise: float  # rad/s/√Hz
    accel_noise: float  # m/s²/√Hz
    gyro_walk: float  # rad/s²/√Hz
    accel_walk: float  # m/s³/√Hz


IMU_NOISE_FIELDS = ("imu_gyro_noise", "imu_accel_noise", "imu_gyro_walk", "imu_accel_walk")  # calibration, CameraProperties

# The D455's IMU (Bosch BMI055/BMI085 datasheets: gyro 0.014 deg/s/√Hz, accelerometer 150-160 µg/√Hz);
# the random walks are typical of those MEMS parts in Kalibr calibrations.
D455 = ImuNoise(gyro_noise=2.44e-4, accel_noise=1.57e-3, gyro_walk=2.0e-5, accel_walk=3.0e-4)


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples in time order: (N,) int64 stamps (ns), (N, 3) gyro rad/s and accel m/s² (float64)."""

    stamp_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    # the accelerometer's own samples (stamps, values) where `accel` is them interpolated at the
    # gyro's stamps (`unite`): what its noise is measured on (interpolation averages the noise away)
    raw_accel: tuple[np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.stamp_ns)

    def between(self, after_ns: int, upto_ns: int) -> ImuSamples:
        """The samples with after_ns < stamp <= upto_ns."""
        lo, hi = np.searchsorted(self.stamp_ns, [after_ns, upto_ns], side="right")
        return ImuSamples(self.stamp_ns[lo:hi], self.gyro[lo:hi], self.accel[lo:hi])

    @staticmethod
    def empty() -> ImuSamples:
        return ImuSamples(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))


def unite(gyro_ns: np.ndarray, gyro: np.ndarray, accel_ns: np.ndarray, accel: np.ndarray) -> ImuSamples:
    """Gyro samples with the accelerometer linearly interpolated at their stamps (held at the ends)."""
    gyro_ns, accel_ns = np.asarray(gyro_ns, np.int64), np.asarray(accel_ns, np.int64)
    acc = np.asarray(accel, np.float64).reshape(-1, 3)
    if len(accel_ns) == 0:
        return ImuSamples.empty()
    t = (gyro_ns - accel_ns[0]).astype(np.float64)
    ta = (accel_ns - accel_ns[0]).astype(np.float64)
    out = np.stack([np.interp(t, ta, acc[:, k]) for k in range(3)], axis=1)
    return ImuSamples(gyro_ns, np.asarray(gyro, np.float64).reshape(-1, 3), out, (accel_ns, acc))


def read_imu_txt(path: Path) -> ImuSamples:
    """A TUM-layout folder's `imu.txt`: `timestamp wx wy wz ax ay az` per line (seconds, rad/s, m/s²),
    `#` comments; in time order. InputError names the line that is not."""
    stamps, rows = [], []
    with open(path) as fh:
        for n, line in enumerate(fh, 1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            parts = line.split()
            try:
                values = [float(p) for p in parts[:7]]
            except ValueError:
                values = []
            if len(values) < 7 or not np.isfinite(values).all():
                raise InputError(f"{path}:{n}: want 'timestamp wx wy wz ax ay az', got {line.strip()[:60]!r}")
            stamps.append(round(values[0] * 1e9))
            rows.append(values[1:])
    if not rows:
        raise InputError(f"{path}: no IMU samples")
    t = np.array(stamps, np.int64)
    if (np.diff(t) <= 0).any():
        n = int(np.argmax(np.diff(t) <= 0)) + 2
        raise InputError(f"{path}: sample {n}: stamps must increase")
    a = np.array(rows, np.float64)
    return ImuSamples(t, a[:, :3].copy(), a[:, 3:].copy())
