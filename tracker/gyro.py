"""The gyro against vision: the check of its rotations (`GyroCheck`) and its bias (`GyroBias`).

Both read spans of placed frames (`GyroSpan`): the rotation over the span as the gyro has it
(preintegrated with the current biases) and as vision placed the frames.

- The check: over the newest GYRO_CHECK_SPANS spans of GYRO_CHECK_FRAMES frames turning at least
  GYRO_CHECK_MIN_RAD, the median of vision's rotation against the gyro's, relative to the angle
  turned, must be at most GYRO_AGREE_RATIO.
- The bias: each span of GYRO_SPAN frames adds its rotation residual to running normal equations
  (forgetting over GYRO_MEMORY_S); the bias is their solution.
"""

from __future__ import annotations

from typing import NamedTuple

import gtsam
import numpy as np

from octolog.kit.imu import ImuNoise
from octolog.tracker.pose import so3_log
from octolog.tracker.preintegration import EPS_BIAS, Segments, bias_corrected

GYRO_SPAN = 6  # frames each gyro-bias rotation spans (200 ms at 30 fps)
GYRO_MEMORY_S = 30.0  # the gyro-bias estimate forgets older rotations over this long (bias drift)
VISUAL_ROTATION_SIGMA = 3e-4  # rad: a tracked frame's rotation error
MAX_ROTATION_RESIDUAL = np.radians(2.0)  # a span the gyro disagrees with more is not evidence (a bad pose)
# a span turning faster is no evidence for the gyro's bias: its images are blurred, vision's
# rotations uncertain
MAX_EVIDENCE_RATE = np.radians(60.0)
GYRO_BIAS_SIGMA = np.radians(1.0)  # rad/s: the gyro bias's prior spread
# Vision checks the gyro: over the newest GYRO_CHECK_SPANS spans of GYRO_CHECK_FRAMES frames turning
# at least GYRO_CHECK_MIN_RAD, the median of vision's rotation against the gyro's, relative to the
# angle turned, must be at most GYRO_AGREE_RATIO. A camera-IMU rotation off by some 15 degrees or
# more fails (its residual is that angle's share of every turn), as do swapped axes and a made-up
# IMU; vision's own rotation over two frames of a heavily blurred first turn erred by up to 0.2.
# A gyro that fails predicts nothing (the motion model's constant velocity), and the gyro is a prior
# of the pose fit and a back-end factor only once at least one span has passed (`confirmed`)
GYRO_CHECK_SPANS = 15
GYRO_CHECK_FRAMES = 2  # frames each checked span covers: the first check two frames in
GYRO_CHECK_MIN_RAD = np.radians(1.0)  # a span turning less says little about the axes
GYRO_AGREE_RATIO = 0.25
# A gyro's rotation is off by this fraction of the angle turned (the path's, there and back): its
# scale-factor and cross-axis errors (BMI055: about 1 % each), a camera-IMU rotation known to a
# fraction of a degree, and the discrete integration of a fast-changing rate
GYRO_SCALE_ERROR = 0.01


class GyroSpan(NamedTuple):
    """An unbroken chain of placed frames with the IMU between them."""

    pim: gtsam.PreintegratedImuMeasurements  # the span's preintegration
    seconds: float
    gyro: np.ndarray  # imu_first_from_imu_last (3x3) as the gyro has it, with the current biases
    vision: np.ndarray  # the same as vision placed the frames
    rate_change: np.ndarray = np.zeros(3)  # the gyro's rate at the span's end less at its start (rad/s)


class GyroCheck:
    """Vision's record of the gyro's rotations: the newest turning spans' residuals."""

    def __init__(self) -> None:
        self._residuals: list[float] = []  # over the angle turned

    def add(self, span: GyroSpan) -> None:
        """A span of GYRO_CHECK_FRAMES frames, vision's rotation against the gyro's, relative to the
        angle turned (a span turning less than GYRO_CHECK_MIN_RAD is no evidence)."""
        turned = max(float(np.linalg.norm(so3_log(span.gyro))), float(np.linalg.norm(so3_log(span.vision))))
        if turned >= GYRO_CHECK_MIN_RAD:
            residual = float(np.linalg.norm(so3_log(span.gyro.T @ span.vision))) / turned
            self._residuals = [*self._residuals[-GYRO_CHECK_SPANS + 1:], residual]

    @property
    def trusted(self) -> bool:
        """Vision does not contradict the gyro's rotations: the median relative residual of the
        newest GYRO_CHECK_SPANS turning spans is at most GYRO_AGREE_RATIO (true before the first)."""
        return not self._residuals or float(np.median(self._residuals)) <= GYRO_AGREE_RATIO

    @property
    def confirmed(self) -> bool:
        """`trusted` after at least one turning span."""
        return bool(self._residuals) and self.trusted


class GyroBias:
    """The gyro's bias from vision's rotations: running normal equations with a prior of
    GYRO_BIAS_SIGMA, forgetting over GYRO_MEMORY_S."""

    def __init__(self, noise: ImuNoise) -> None:
        self._gyro_noise = noise.gyro_noise
        self.bg = np.zeros(3)
        self._H, self._g = np.eye(3) / GYRO_BIAS_SIGMA**2, np.zeros(3)

    def set_noise(self, noise: ImuNoise) -> None:
        """The gyro's white noise from here on (a measured one in place of the datasheet's)."""
        self._gyro_noise = noise.gyro_noise

    def restart(self, bg: np.ndarray) -> None:
        """Start again from `bg` (its spans were read through a wrong camera-IMU rotation)."""
        self._H = np.eye(3) / GYRO_BIAS_SIGMA**2
        self._g = self._H @ np.asarray(bg, float)
        self.bg = np.asarray(bg, float).copy()

    def add(self, span: GyroSpan, ba: np.ndarray) -> bool:
        """A span of GYRO_SPAN frames (preintegrated with the accelerometer's bias `ba` and `bg`) into
        the normal equations; False when it is no evidence (a bad pose, or a turn too fast)."""
        pim, dt, R0, vis = span.pim, span.seconds, span.gyro, span.vision
        r = so3_log(R0.T @ vis)
        if np.linalg.norm(r) > MAX_ROTATION_RESIDUAL or np.linalg.norm(so3_log(R0)) > MAX_EVIDENCE_RATE * dt:
            return False
        J = np.zeros((3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = EPS_BIAS
            Rk, _, _ = bias_corrected(pim, ba, self.bg + e)
            J[:, k] = so3_log(R0.T @ Rk) / EPS_BIAS  # d rotation / d bias
        # r(b) ~ r(bg) - J (b - bg): J b ~ r + J bg
        sigma2 = 2 * VISUAL_ROTATION_SIGMA**2 + self._gyro_noise**2 * dt
        forget = np.exp(-dt / GYRO_SPAN / GYRO_MEMORY_S)
        prior = np.eye(3) / GYRO_BIAS_SIGMA**2
        self._H = prior + forget * (self._H - prior) + J.T @ J / sigma2
        self._g = forget * self._g + J.T @ (r + J @ self.bg) / sigma2
        self.bg = np.linalg.solve(self._H, self._g)
        return True

    def rotation_sigma(self, segments: Segments) -> float:
        """The gyro's rotation error over an interval's pieces (rad): its white noise, the bias
        estimate's uncertainty, and GYRO_SCALE_ERROR of the angle turned along the way."""
        dt = float(segments[0].sum())
        bias_sigma = float(np.sqrt(np.linalg.eigvalsh(np.linalg.inv(self._H)).max()))
        turned = float(np.linalg.norm(segments[1] - self.bg, axis=1) @ segments[0])  # the path's angle, not the net
        sigma = np.sqrt(self._gyro_noise**2 * dt + (bias_sigma * dt) ** 2 + (GYRO_SCALE_ERROR * turned) ** 2)
        return float(sigma)
