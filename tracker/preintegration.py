"""The IMU's samples and the frames between them, and the preintegration of an interval.

- `ImuBuffer` holds the samples not yet consumed and cuts an interval into pieces (dt, gyro, accel)
  between consecutive samples.
- `Preintegrator` preintegrates pieces with gtsam's `PreintegratedImuMeasurements` (Forster et
  al.'s on-manifold preintegration) for given biases; `bias_corrected` re-applies a changed bias
  to first order, which also gives the bias Jacobians by differences (`EPS_BIAS`), with no
  re-integration.
- `FrameHistory` holds the newest frames' poses in the IMU's frame, each with the pieces since the
  frame before: the chains of frames the gyro check, the gyro's bias and the gravity alignment read.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from octolog.kit.imu import ImuNoise, ImuSamples

MAX_GAP_NS = 100_000_000  # an IMU silent this long between samples leaves the interval unmeasured
EPS_BIAS = 1e-4  # the bias step of the Jacobians taken by differences

Segments = tuple[np.ndarray, np.ndarray, np.ndarray]  # pieces of an interval: dt (s), gyro, accel


class ImuBuffer:
    """The samples in time order, from the newest frame's on."""

    def __init__(self) -> None:
        self._t = np.zeros(0, np.int64)
        self._w = np.zeros((0, 3))
        self._a = np.zeros((0, 3))
        self.late_ns = 0  # the IMU's clock runs this late: every sample is held this much earlier

    def add(self, samples: ImuSamples) -> int:
        """Samples in time order (older than the newest held: ignored); how many were kept."""
        if len(samples) == 0:
            return 0
        stamps = samples.stamp_ns - self.late_ns
        keep = stamps > (self._t[-1] if self._t.size else np.iinfo(np.int64).min)
        self._t = np.concatenate([self._t, stamps[keep]])
        self._w = np.concatenate([self._w, samples.gyro[keep]])
        self._a = np.concatenate([self._a, samples.accel[keep]])
        return int(keep.sum())

    def segments(self, t0: int, t1: int) -> Segments | None:
        """Pieces (dt s, gyro, accel) covering [t0, t1] between consecutive samples, each with the
        samples' values interpolated at its middle (as ORB-SLAM3 averages consecutive samples: holding
        a sample until the next lags a changing rate by half a sample period, a 0.06 deg error over a
        keyframe interval of a fast turn); None where the IMU does not cover the interval."""
        t = self._t
        if t.size == 0 or t1 <= t0 or t[0] > t0 or t[-1] < t1 - MAX_GAP_NS:
            return None
        lo = int(np.searchsorted(t, t0, side="right")) - 1
        hi = int(np.searchsorted(t, t1, side="left"))
        edges = np.concatenate([[t0], t[lo + 1:hi], [t1]])
        if np.diff(edges).max() > MAX_GAP_NS:
            return None
        mid = (edges[:-1] + edges[1:]) // 2
        tk = t[lo:hi + 1] - t0  # the samples around the interval, as small numbers
        w = np.stack([np.interp(mid - t0, tk, self._w[lo:hi + 1, k]) for k in range(3)], axis=1)
        a = np.stack([np.interp(mid - t0, tk, self._a[lo:hi + 1, k]) for k in range(3)], axis=1)
        return np.diff(edges) * 1e-9, w, a

    def retime(self, more_late_ns: int) -> None:
        """The IMU's clock runs `more_late_ns` later than held: the samples move back by it."""
        self._t = self._t - more_late_ns
        self.late_ns += more_late_ns

    def trim(self, stamp_ns: int) -> None:
        """Drop the samples before the last one at or before `stamp_ns` (no interval starts earlier)."""
        cut = int(np.searchsorted(self._t, stamp_ns, side="left")) - 1
        if cut > 0:
            self._t, self._w, self._a = self._t[cut:], self._w[cut:], self._a[cut:]


class Preintegrator:
    """Preintegration with one IMU's noise (gravity is left to the caller: it is not known here)."""

    def __init__(self, noise: ImuNoise) -> None:
        self.set_noise(noise)

    def set_noise(self, noise: ImuNoise) -> None:
        """The IMU's noise from here on (a measured one in place of the datasheet's)."""
        p = gtsam.PreintegrationParams(np.zeros(3))
        p.setGyroscopeCovariance(np.eye(3) * noise.gyro_noise**2)
        p.setAccelerometerCovariance(np.eye(3) * noise.accel_noise**2)
        p.setIntegrationCovariance(np.eye(3) * 1e-8)
        self._params = p

    def integrate(self, segments: Segments, ba: np.ndarray, bg: np.ndarray) -> gtsam.PreintegratedImuMeasurements:
        """The pieces preintegrated with the accelerometer's bias `ba` and the gyro's `bg` taken out."""
        pim = gtsam.PreintegratedImuMeasurements(self._params, gtsam.imuBias.ConstantBias(ba, bg))
        for dt, w, a in zip(*segments):
            if dt > 0:
                pim.integrateMeasurement(a, w, float(dt))
        return pim


def bias_corrected(pim: gtsam.PreintegratedImuMeasurements, ba: np.ndarray, bg: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ΔR, Δp, Δv) of an interval for biases (ba, bg), first order about its integration's."""
    s = pim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(ba, bg))
    return s.attitude().matrix(), np.asarray(s.position()), np.asarray(s.velocity())


def joined(parts: list[Segments]) -> Segments:
    """Consecutive intervals' pieces (dt, gyro, accel) as one interval's."""
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))  # type: ignore[return-value]


@dataclass
class FrameRecord:
    stamp_ns: int
    world_from_imu: np.ndarray  # (4, 4)
    visual: bool  # placed by vision (else propagated: INERTIAL)
    continuous: bool  # the step from the record before it is motion (not a relocalisation)
    segments: Segments | None  # dt, gyro, accel since the record before


def chain_segments(records: list[FrameRecord]) -> Segments:
    """The pieces from the first of an unbroken chain of records to its last."""
    return joined([r.segments for r in records[1:]])  # type: ignore[misc]


class FrameHistory:
    """The newest frames, placed by vision or propagated, oldest first."""

    def __init__(self) -> None:
        self._records: list[FrameRecord] = []

    @property
    def last(self) -> FrameRecord | None:
        return self._records[-1] if self._records else None

    def append(self, record: FrameRecord) -> None:
        self._records.append(record)

    def chain(self, n: int) -> list[FrameRecord] | None:
        """The newest n+1 records if they are one unbroken chain of visual frames with IMU between."""
        recs = self._records[-(n + 1):]
        if len(recs) < n + 1 or not all(r.visual for r in recs) or \
                not all(r.continuous and r.segments is not None for r in recs[1:]):
            return None
        return recs

    def newest_chain(self, window_s: float) -> list[FrameRecord]:
        """The newest visual records over `window_s`, back to the first break in the chain of motion
        (empty when the newest is not visual)."""
        newest = self._records[-1].stamp_ns
        out: list[FrameRecord] = []
        for r in reversed(self._records):
            if not r.visual or (newest - r.stamp_ns) * 1e-9 > window_s:
                break
            out.append(r)
            if not r.continuous or r.segments is None:
                break  # it starts the chain
        out.reverse()
        return out

    def segments_since(self, stamp_ns: int) -> list[Segments] | None:
        """Each interval's pieces from the record at `stamp_ns` to the newest; None when that record
        is gone or the chain since it is broken (a relocalisation, or an interval without IMU)."""
        since = [r for r in self._records if r.stamp_ns > stamp_ns]
        if not any(r.stamp_ns == stamp_ns for r in self._records) or \
                not all(r.continuous and r.segments is not None for r in since):
            return None
        return [r.segments for r in since]  # type: ignore[misc]

    def since_visual_s(self, stamp_ns: int) -> float:
        """Seconds from the newest frame vision placed to `stamp_ns` (inf: none)."""
        last_visual = next((r.stamp_ns for r in reversed(self._records) if r.visual), None)
        return float("inf") if last_visual is None else (stamp_ns - last_visual) * 1e-9

    def rebase(self, correction: np.ndarray) -> None:
        """The map moved (4x4 world_new_from_world_old): so do the poses."""
        for r in self._records:
            r.world_from_imu = correction @ r.world_from_imu

    def remount(self, old_imu_from_new_imu: np.ndarray) -> None:
        """The IMU is placed otherwise on the camera (4x4): the frames' IMU poses move with it."""
        for r in self._records:
            r.world_from_imu = r.world_from_imu @ old_imu_from_new_imu

    def trim(self, keep_from_ns: int, keep_at_least: int) -> None:
        """Drop records older than `keep_from_ns`, keeping at least `keep_at_least`."""
        while len(self._records) > keep_at_least and self._records[0].stamp_ns < keep_from_ns:
            self._records.pop(0)
