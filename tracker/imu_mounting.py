"""Where the IMU sits on the camera and how late its clock runs, from vision's rotations: the
camera-IMU rotation and the time offset a calibration file or the device states, measured online
(as VINS-Mono and OpenVINS do), since a unit nobody calibrated is off by degrees and milliseconds.

Both read the spans of placed frames the gyro's bias reads (`GyroSpan`: the rotation over the span
as the gyro has it, and as vision placed the frames):

- The rotation: vision's rotation vectors in the camera frame against the gyro's in the IMU frame,
  theta_camera = camera_from_imu theta_imu over every span that turned, solved as Wahba's problem
  with the gyro's bias (a steady turn about a misplaced axis looks like a bias), as linear least
  squares whose 3x3 is then made the nearest rotation; applied once the turns span two directions
  (the scatter's second eigenvalue at least MIN_EXCITATION: a rotation about one axis only leaves
  the turn about that axis unseen) and each entry is known to within ROTATION_SIGMA_RAD.
- The time offset, in the same least squares: an IMU clock late by L integrates each span's rates
  over [t0 - L, t1 - L], which misses L (w(t1) - w(t0)) of the rotation; applied when known to
  within OFFSET_SIGMA_S.

Deterministic: the same spans give the same estimates.
"""

from __future__ import annotations

import numpy as np

from octolog.tracker.gyro import GYRO_CHECK_MIN_RAD as MIN_TURN_RAD  # a span turning less says little about the axes
from octolog.tracker.gyro import MAX_EVIDENCE_RATE as MAX_TURN_RATE  # faster: blurred images, vision's rotation uncertain
from octolog.tracker.gyro import VISUAL_ROTATION_SIGMA
from octolog.tracker.pose import so3_log

MIN_EXCITATION = 0.02  # rad²: the turns' scatter in its second direction before the rotation is solved
# A span whose gyro and vision disagree by more than this share of its turn (plus MAX_RESIDUAL_RAD)
# is a bad pose, not evidence (a rotation off by 15 degrees is a quarter of each turn)
MAX_RESIDUAL_SHARE = 0.3
MAX_RESIDUAL_RAD = np.radians(1.0)
ROTATION_SIGMA_RAD = np.radians(0.3)  # the rotation is applied once each of its entries is known to within this
OFFSET_SIGMA_S = 0.5e-3  # the time offset is applied once known to within this
MAX_OFFSET_S = 0.05  # an estimate further out is no clock offset (a bad span, a dropped frame)


N_PARAMS = 13  # camera_from_imu's 3x3 (a linear map, made a rotation after), the gyro's bias in the camera frame, the offset


class ImuMounting:
    """The camera-IMU rotation and the IMU clock's lateness, estimated from spans of placed frames."""

    def __init__(self, camera_from_imu: np.ndarray, late_s: float = 0.0) -> None:
        self.stated = np.asarray(camera_from_imu, float)[:3, :3].copy()  # what the calibration said
        self.rotation = self.stated.copy()  # camera_from_imu's rotation as estimated
        self.late_s = late_s  # the IMU's clock is this late (its samples are moved back by it)
        self._normal = np.zeros((N_PARAMS, N_PARAMS))  # the joint least squares' normal equations
        self._rhs = np.zeros(N_PARAMS)
        self._yy = 0.0  # the observations' sum of squares (for the residual's spread)
        self._n = 0  # spans taken
        self._scatter = np.zeros((3, 3))  # sum of theta_imu theta_imu^T

    def add(self, gyro: np.ndarray, vision_imu: np.ndarray, rate_change: np.ndarray, seconds: float,
            gyro_bias: np.ndarray) -> None:
        """A span: its rotation as the gyro has it (imu_first_from_imu_last, with the bias
        `gyro_bias` and the current offset), as vision placed the frames (the same, through the
        current rotation estimate), the gyro's rate at its end less its rate at its start (rad/s,
        IMU frame), and its length. One row per axis of
        theta_camera + late_applied g = M theta_raw - c seconds + late g, g = rotation rate_change,
        where theta_raw is the gyro's rotation without a bias: the bias is estimated along (a steady
        turn's misplaced axis looks like one)."""
        theta_imu = so3_log(gyro)
        theta_camera = self.rotation @ so3_log(vision_imu)
        turned = float(np.linalg.norm(theta_imu))
        if turned < MIN_TURN_RAD or turned > MAX_TURN_RATE * seconds:
            return
        if np.linalg.norm(theta_camera - self.rotation @ theta_imu) > MAX_RESIDUAL_SHARE * turned + MAX_RESIDUAL_RAD:
            return
        raw = theta_imu + np.asarray(gyro_bias, float) * seconds
        g = self.rotation @ rate_change
        y = theta_camera + self.late_s * g
        for k in range(3):
            row = np.zeros(N_PARAMS)
            row[3 * k:3 * k + 3] = raw
            row[9 + k] = -seconds
            row[12] = g[k]
            self._normal += np.outer(row, row)
            self._rhs += row * y[k]
            self._yy += float(y[k] * y[k])
        self._scatter += np.outer(theta_imu, theta_imu)
        self._n += 1

    @property
    def excitation(self) -> float:
        """The turns' scatter in its second direction (rad²)."""
        return float(np.linalg.eigvalsh(self._scatter)[1])

    def _solve(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The parameters and their covariance (None: too few spans to solve)."""
        if self.excitation < MIN_EXCITATION or self._n < N_PARAMS:
            return None
        try:
            cov = np.linalg.inv(self._normal)
        except np.linalg.LinAlgError:
            return None
        p = cov @ self._rhs
        rss = max(self._yy - float(p @ self._rhs), 0.0)
        sigma2 = max(rss / max(3 * self._n - N_PARAMS, 1), VISUAL_ROTATION_SIGMA**2)
        return p, cov * sigma2

    def solve_rotation(self) -> np.ndarray | None:
        """camera_from_imu's rotation from the spans so far (the nearest rotation to the fitted
        linear map; None: the turns have not spanned two directions yet)."""
        solved = self._solve()
        if solved is None or np.sqrt(np.diag(solved[1])[:9]).max() > ROTATION_SIGMA_RAD:
            return None
        u, _, vt = np.linalg.svd(solved[0][:9].reshape(3, 3))
        d = np.sign(np.linalg.det(u @ vt))
        return u @ np.diag([1.0, 1.0, d]) @ vt

    def solve_bias(self) -> np.ndarray:
        """The gyro's bias (IMU frame, rad/s) fitted along with the rotation (zeros: not solved)."""
        solved = self._solve()
        if solved is None:
            return np.zeros(3)
        return self.rotation.T @ solved[0][9:12]

    def solve_late(self) -> float | None:
        """How late the IMU's clock runs (s); None until known to within OFFSET_SIGMA_S."""
        solved = self._solve()
        if solved is None or np.sqrt(solved[1][12, 12]) > OFFSET_SIGMA_S:
            return None
        late = float(solved[0][12])
        return late if abs(late) <= MAX_OFFSET_S else None

    @property
    def rotation_change_deg(self) -> float:
        """The angle between the estimated camera-IMU rotation and the stated one."""
        c = (np.trace(self.stated.T @ self.rotation) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
