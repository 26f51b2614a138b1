"""Up from an accelerometer: the arithmetic shared by the replay's sources (files) and the mapper
(a live camera's IMU on the bus). See octolog.replay.source_gravity for where the samples come from.

At rest an accelerometer measures the reaction to gravity, +9.81 m/s² pointing up. The samples
within WINDOW_S of the first frame are averaged and rotated into the colour camera's optical frame.
A consumer accelerometer's bias is worth degrees, so `level_on_plane` then takes the normal of the
first frame's dominant near-horizontal plane (a floor, a table) when there is one.
"""

from __future__ import annotations

import threading

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import RgbdFrame

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

    @property
    def heard(self) -> bool:
        """Whether any accelerometer sample has arrived."""
        with self._lock:
            return bool(self._samples)

    def up_at(self, stamp_ns: int, color_frame: str, where: str) -> np.ndarray | None:
        """Up in `color_frame` from the samples within WINDOW_S of `stamp_ns` (None without any);
        InputError when their mean is not about g."""
        with self._lock:
            rows = [s[1:] for s in self._samples if abs(s[0] - stamp_ns) <= WINDOW_S * 1e9]
            rotation = rotation_between(self._parent_from_child, color_frame, self._accel_frame)
        return up_from_samples(np.array(rows, dtype=np.float64).reshape(-1, 3), rotation, where)


# Levelling on a horizontal plane: the largest plane of frame 0 whose normal is this close to the
# accelerometer's up, with at least this share of the frame's depth points, gives up instead (a floor
# or a table is level to a fraction of a degree; a consumer accelerometer's bias is worth degrees).
PLANE_MAX_DEG = 5.0
PLANE_MIN_SHARE = 0.05
PLANE_TOLERANCE_M = 0.01
PLANE_TRIES = 300
PLANE_STRIDE = 4  # every 4th pixel in each direction
PLANE_MIN_SPREAD = 0.3  # a patch: its second extent at least this share of its first
PLANE_REFITS = 4  # least-squares refits of a hypothesis (LO-RANSAC)
PLANE_MIN_CROWDING = 0.65  # inliers in the inner half of the tolerance: 0.5 if spread evenly


def level_on_plane(up: np.ndarray, frame: RgbdFrame) -> tuple[np.ndarray, bool]:
    """(up, levelled): `up` replaced by the normal of frame 0's dominant near-horizontal plane when
    there is one (see PLANE_*), else `up` as it was. RANSAC with a fixed seed, then a least-squares
    fit to the inliers: the same frame gives the same bytes."""
    K = frame.intrinsics
    depth = frame.depth[::PLANE_STRIDE, ::PLANE_STRIDE].astype(np.float64) * frame.depth_scale_m
    v, u = np.nonzero(depth > 0)
    if v.size < 100:
        return up, False
    z = depth[v, u]
    u, v = u * PLANE_STRIDE, v * PLANE_STRIDE
    P = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], axis=1)
    rng = np.random.default_rng(0)
    cos_max = np.cos(np.radians(PLANE_MAX_DEG))
    best, best_count = None, int(PLANE_MIN_SHARE * len(P))
    for idx in rng.integers(0, len(P), (PLANE_TRIES, 3)):
        n = np.cross(P[idx[1]] - P[idx[0]], P[idx[2]] - P[idx[0]])
        norm = float(np.linalg.norm(n))
        if norm < 1e-12 or abs(n @ up) / norm < cos_max:
            continue
        n /= norm
        inliers = np.abs((P - P[idx[0]]) @ n) < PLANE_TOLERANCE_M
        count = int(inliers.sum())
        if count > best_count and (fit := _refine_plane(P, inliers, up, cos_max)) is not None:
            best, best_count = fit
    return (best, True) if best is not None else (up, False)


def _refine_plane(P: np.ndarray, inliers: np.ndarray, up: np.ndarray,
                  cos_max: float) -> tuple[np.ndarray, int] | None:
    """(normal towards up, support) of the plane a RANSAC hypothesis leads to: fitted to its inliers
    by least squares, the inliers taken again around the fit, PLANE_REFITS times (LO-RANSAC). A
    hypothesis that cuts through a surface (a band a few cm wide across the floor) drifts onto that
    surface, and is then judged by that surface's normal. None when the result is not a patch (a
    strip) or not one surface (its points spread evenly across the tolerance), leaves the window
    around up, or loses its support."""
    for _ in range(PLANE_REFITS):
        Q = P[inliers]
        if len(Q) < 3:
            return None
        centre = Q.mean(axis=0)
        _, sv, vt = np.linalg.svd(Q - centre, full_matrices=False)
        normal = vt[2] if vt[2] @ up > 0 else -vt[2]
        distance = np.abs((P - centre) @ normal)
        inliers = distance < PLANE_TOLERANCE_M
    count = int(inliers.sum())
    # a surface's points crowd around its plane (depth noise); a plane through bands of several
    # surfaces has its points spread evenly across the tolerance (half of them in its inner half)
    crowded = np.mean(distance[inliers] < 0.5 * PLANE_TOLERANCE_M) if count else 0.0
    if (sv[1] < PLANE_MIN_SPREAD * sv[0] or crowded < PLANE_MIN_CROWDING or normal @ up < cos_max
            or count < PLANE_MIN_SHARE * len(P)):
        return None
    return normal, count
