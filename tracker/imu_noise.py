"""The IMU's white noise, measured from its own samples: what the tracker weighs the gyro and the
accelerometer by, in place of the datasheet's figures (`ImuNoise`), which a mounted unit rarely meets.

A sample is the motion plus white noise of standard deviation density / sqrt(dt). The motion of a
hand-held or robot-borne camera is smooth at the IMU's rate, so the third difference of consecutive
samples, x[k+3] - 3 x[k+2] + 3 x[k+1] - x[k], all but removes it (a 150 deg/s turn over 0.3 s leaves
a quarter of the datasheet noise's share) while the noise's variance grows by a factor of 20 (the
sum of the squared binomial weights). The scale of those differences, taken robustly (the median of
their magnitudes: a jolt or a dropped sample touches a few), over the newest WINDOW_S of samples,
gives the density. Deterministic: it reads the samples up to the frame it is asked at, however
they arrived.

The bias random walks are not measured (a drift of a few thousandths of a degree per second over
minutes needs much longer than a session's first minute): they stay the datasheet's, scaled by the
same factor as the white noise of their sensor.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.imu import ImuNoise, ImuSamples

WINDOW_S = 30.0  # the newest samples measured
MIN_SAMPLES = 400  # at least this many differences of each sensor before the first estimate (2-4 s)
THIRD_DIFFERENCE_VARIANCE = 20.0  # 1 + 9 + 9 + 1
MAD_TO_SIGMA = 1.482602218505602  # the median of |N(0, 1)|'s reciprocal
GAP_RATIO = 1.5  # consecutive samples further apart than this times the median period: a gap


class _Stream:
    """One sensor's newest samples."""

    def __init__(self) -> None:
        self.t = np.zeros(0, np.int64)
        self.x = np.zeros((0, 3))

    def add(self, stamps: np.ndarray, values: np.ndarray) -> None:
        keep = stamps > (self.t[-1] if self.t.size else np.iinfo(np.int64).min)
        self.t = np.concatenate([self.t, stamps[keep]])
        self.x = np.concatenate([self.x, np.asarray(values, float).reshape(-1, 3)[keep]])
        if self.t.size and self.t[-1] - self.t[0] > 2 * WINDOW_S * 1e9:
            keep = self.t >= self.t[-1] - int(WINDOW_S * 1e9) - 1_000_000_000
            self.t, self.x = self.t[keep], self.x[keep]

    def density(self, upto_ns: int) -> float | None:
        """The white-noise density over the newest WINDOW_S up to `upto_ns` (None: too few samples)."""
        hi = int(np.searchsorted(self.t, upto_ns, side="right"))
        lo = int(np.searchsorted(self.t, upto_ns - int(WINDOW_S * 1e9), side="left"))
        t, x = self.t[lo:hi], self.x[lo:hi]
        if t.size < MIN_SAMPLES + 3:
            return None
        dt = np.diff(t)
        period = float(np.median(dt))
        even = dt <= GAP_RATIO * period
        ok = even[:-2] & even[1:-1] & even[2:]  # the four samples of each difference evenly spaced
        if int(ok.sum()) < MIN_SAMPLES:
            return None
        d3 = x[3:] - 3.0 * x[2:-1] + 3.0 * x[1:-2] - x[:-3]
        sigma = MAD_TO_SIGMA * np.median(np.abs(d3[ok])) / np.sqrt(THIRD_DIFFERENCE_VARIANCE)
        return float(sigma * np.sqrt(period * 1e-9))


class NoiseMeter:
    """Measures the gyro's and the accelerometer's white-noise densities from the samples."""

    def __init__(self, datasheet: ImuNoise) -> None:
        self.datasheet = datasheet
        self._gyro, self._accel = _Stream(), _Stream()

    def add(self, samples: ImuSamples) -> None:
        """Samples in time order (those not newer than the newest held are ignored); the
        accelerometer's own samples when they came united onto the gyro's stamps."""
        self._gyro.add(samples.stamp_ns, samples.gyro)
        if samples.raw_accel is not None:
            self._accel.add(*samples.raw_accel)
        else:
            self._accel.add(samples.stamp_ns, samples.accel)

    def measure(self, upto_ns: int) -> ImuNoise | None:
        """The densities over the newest WINDOW_S of samples up to `upto_ns` (None: too few yet)."""
        gyro, accel = self._gyro.density(upto_ns), self._accel.density(upto_ns)
        if gyro is None or accel is None:
            return None
        d = self.datasheet
        return ImuNoise(gyro_noise=gyro, accel_noise=accel, gyro_walk=d.gyro_walk * gyro / d.gyro_noise,
                        accel_walk=d.accel_walk * accel / d.accel_noise)
