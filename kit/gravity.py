"""Up from an accelerometer: the arithmetic shared by the replay's sources (files) and the mapper
(a live camera's IMU on the bus). See octolog.replay.gravity for where the samples come from.

At rest an accelerometer measures the reaction to gravity, +9.81 m/s² pointing up. The samples
within WINDOW_S of the first frame are averaged and rotated into the colour camera's optical frame.
"""

from __future__ import annotations

import threading

import numpy as np

from octolog.kit.errors import InputError

G = 9.80665
WINDOW_S = 0.1  # samples this close to the first frame are averaged
# a mean this far from g is no rest reading (the camera was accelerating, or the units are wrong)
MAX_G_ERROR = 0.25


def up_from_samples(samples: np.ndarray, to_optical: np.ndarray, where: str) -> np.ndarray | None:
    """The mean of (N, 3) accelerometer samples as a unit up vector in the optical frame (rotated
    by `to_optical`); None when there are none. InputError when their mean is not about g (wrong
    units, or no rest reading)."""
    if samples.shape[0] == 0:
        return None
    mean = samples.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    if not np.isfinite(norm) or abs(norm - G) > MAX_G_ERROR * G:
        raise InputError(f"{where}: the accelerometer's mean near the first frame is {norm:.2f} m/s², "
                         f"not about g ({G:.2f}): wrong units, or the camera was not near rest; "
                         f"set mapper.grid_up to say which way is up")
    return to_optical @ (mean / norm)


def rotation_between(parent_from_child: dict[str, tuple[str, np.ndarray]], target: str, source: str) -> np.ndarray:
    """target_from_source rotation through a static tree (child -> (parent, parent_from_child));
    identity when either frame is not in it."""
    def to_root(frame: str) -> tuple[str, np.ndarray]:
        R = np.eye(3)
        for _ in range(16):  # a tree, not a cycle
            if frame not in parent_from_child:
                break
            parent, P = parent_from_child[frame]
            R, frame = P @ R, parent
        return frame, R
    root_t, root_from_target = to_root(target)
    root_s, root_from_source = to_root(source)
    if not target or not source or root_t != root_s:
        return np.eye(3)
    return root_from_target.T @ root_from_source


class LiveUp:
    """Up at a live stream's first frame, from accelerometer samples and static transforms as they
    arrive on the bus (a camera's `camera/accel/sample` and `/tf_static`). Thread-safe: the bus's
    callbacks add, the mapper asks. Holds at most MAX_SAMPLES samples (the latest) until asked."""

    MAX_SAMPLES = 4000  # 20 s of a 200 Hz IMU

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._samples: list[tuple[int, float, float, float]] = []
        self._accel_frame = ""
        self._parent_from_child: dict[str, tuple[str, np.ndarray]] = {}

    def add_sample(self, stamp_ns: int, xyz: tuple[float, float, float], frame_id: str) -> None:
        with self._lock:
            self._samples.append((stamp_ns, *xyz))
            if len(self._samples) > 2 * self.MAX_SAMPLES:
                del self._samples[:-self.MAX_SAMPLES]
            self._accel_frame = frame_id

    def add_transform(self, parent: str, child: str, rotation: np.ndarray) -> None:
        with self._lock:
            self._parent_from_child[child] = (parent, rotation)

    def up_at(self, stamp_ns: int, color_frame: str, where: str) -> np.ndarray | None:
        """Up in `color_frame` from the samples within WINDOW_S of `stamp_ns` (None without any);
        InputError when their mean is not about g."""
        with self._lock:
            rows = [s[1:] for s in self._samples if abs(s[0] - stamp_ns) <= WINDOW_S * 1e9]
            rotation = rotation_between(self._parent_from_child, color_frame, self._accel_frame)
        return up_from_samples(np.array(rows, dtype=np.float64).reshape(-1, 3), rotation, where)
