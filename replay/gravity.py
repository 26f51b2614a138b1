"""Which way is up at the first frame: gravity from a source's accelerometer.

The tracker's world is its first camera's optical frame (x right, y down, z forward). The mapper's
`map` frame (grid, REP 103: z up) needs "up" in that frame. A camera is rarely held level, so the
up vector comes from an accelerometer, the way a phone finds it. At rest an accelerometer measures
the reaction to gravity, +9.81 m/s² pointing up. Its samples from 0.1 s before to 0.1 s after the
first frame are averaged and rotated into the colour camera's optical frame.

- TUM RGB-D folders ship `accelerometer.txt`, the Kinect's accelerometer. Its axes are not
  documented with the data. Against fr1/xyz's motion-capture ground truth (z up), at three
  different camera attitudes, up in the optical frame is (-ax, -ay, az): x left, y up, z forward.
  The frame-0 estimate is 1.3 degrees from the ground truth's up.
- The synthetic room simulates a D455's accelerometer: 200 Hz samples of the true up vector, with a
  constant bias and white noise (BMI055-class figures), seeded.

A consumer accelerometer's bias is worth degrees (TUM's Kinect: 0.7 m/s², about 4 degrees, over
the whole of fr1/xyz against the ground truth). So when frame 0 shows a large plane within 5 degrees
of the accelerometer's up (a floor, a table), its normal is taken instead (`level_on_plane`).

A source without an accelerometer gives None. The run then keeps the old assumption (a camera held
level at the start, up = -y) and says so in `summary.json` and the status output.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import RgbdFrame
from octolog.kit.gravity import WINDOW_S, G, rotation_between, up_from_samples

if TYPE_CHECKING:
    from octolog.replay.sources import Source

# TUM's Kinect accelerometer axes in the colour camera's optical frame (see the module docstring;
# `octolog import` writes it into the MCAP as a /tf_static)
KINECT_TO_OPTICAL = np.diag([-1.0, -1.0, 1.0])
# the simulated IMU: 200 Hz, white noise and a per-axis bias of a consumer MEMS accelerometer
SIM_RATE_HZ = 200.0
SIM_NOISE_MS2 = 0.02
SIM_BIAS_MS2 = 0.04


def tum_up(folder: Path, stamp_ns: int) -> np.ndarray | None:
    """Up at `stamp_ns` from a TUM folder's accelerometer.txt (None if the folder has none, or no
    sample within WINDOW_S of the stamp)."""
    path = folder / "accelerometer.txt"
    if not path.is_file():
        return None
    rows = []
    for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        try:
            t, ax, ay, az = (float(p) for p in parts[:4])
        except ValueError:
            raise InputError(f"{path}:{n}: want 'timestamp ax ay az', got {line.strip()[:60]!r}") from None
        if len(parts) < 4:
            raise InputError(f"{path}:{n}: want 'timestamp ax ay az', got {line.strip()[:60]!r}")
        if abs(t - stamp_ns * 1e-9) <= WINDOW_S:
            rows.append((ax, ay, az))
    return up_from_samples(np.array(rows, dtype=np.float64).reshape(-1, 3), KINECT_TO_OPTICAL, str(path))


def simulated_up(world_from_camera_at, stamp_s: float, seed: int) -> np.ndarray:
    """Up at `stamp_s` from a simulated accelerometer rigidly on the camera (world z up):
    `world_from_camera_at(t)` gives the (3, 3) rotation at time t. Its samples are expressed in
    the optical frame of the camera at `stamp_s`: the rotation over +-0.1 s is small and, as with
    a real device, not compensated."""
    rng = np.random.default_rng(seed)
    bias = rng.normal(0.0, SIM_BIAS_MS2, 3)
    times = stamp_s + np.arange(-WINDOW_S, WINDOW_S + 1e-9, 1.0 / SIM_RATE_HZ)
    samples = np.stack([world_from_camera_at(t).T @ np.array([0.0, 0.0, G]) for t in times])
    samples += bias + rng.normal(0.0, SIM_NOISE_MS2, samples.shape)
    return up_from_samples(samples, np.eye(3), "synthetic IMU")


def up_from_metadata(metadata: dict, where: str) -> np.ndarray | None:
    """The up vector a run recorded in its session log's metadata (`gravity.up`), if any."""
    text = metadata.get("gravity", {}).get("up")
    if text is None:
        return None
    try:
        up = np.array(json.loads(text), dtype=np.float64)
    except (ValueError, TypeError):
        up = np.zeros(0)
    if up.shape != (3,) or not np.isfinite(up).all() or not 0.5 < float(np.linalg.norm(up)) < 1.5:
        raise InputError(f"{where}: metadata gravity.up {text[:60]!r} is not a unit 3-vector")
    return up


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


def source_up(source: Source) -> tuple[np.ndarray, str] | None:
    """(up, note) at a file source's first frame: its accelerometer, levelled on frame 0's plane
    when there is one; None without an accelerometer. What `octolog run` gives the mapper as
    `grid_up`, and what the replay publishes on `camera/gravity` for a mapper elsewhere."""
    up = source.gravity_up()
    if up is None:
        return None
    up, levelled = level_on_plane(up, next(iter(source.frames(0, 1))))
    return up, "gravity-aligned (accelerometer" + (", levelled on a horizontal plane of frame 0)" if levelled else ")")


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


def recorded_up(path: Path, first_stamp_ns: int, color_frame: str) -> np.ndarray | None:
    """Up at a recording's first colour frame from its `camera/accel/sample` (sensor_msgs/Imu, the
    realsense-ros topic `octolog record` writes), rotated into the colour camera's optical frame by
    the file's `/tf_static` (None without accelerometer samples near that frame). Without a
    transform from the accelerometer's frame to the colour frame, the two are taken as aligned:
    RealSense IMU optical frames share the cameras' axes."""
    from octolog.kit.mcaplog import read_messages
    from octolog.schemas import codec
    from octolog.schemas.topics import ACCEL, TF_STATIC

    samples, accel_frame, parent_from_child = [], "", {}
    for m in read_messages(path, [ACCEL.name, TF_STATIC.name]):
        msg = codec.decode(m.data, TF_STATIC.msgtype if m.topic == TF_STATIC.name else ACCEL.msgtype)
        if m.topic == TF_STATIC.name:
            for parent, child, T in codec.tf_transforms(msg):
                parent_from_child[child] = (parent, T[:3, :3])
            continue
        t = codec.stamp_ns(msg.header)
        if abs(t - first_stamp_ns) <= WINDOW_S * 1e9:
            a = msg.linear_acceleration
            samples.append((a.x, a.y, a.z))
            accel_frame = msg.header.frame_id
        elif t > first_stamp_ns + WINDOW_S * 1e9:
            break
    rotation = rotation_between(parent_from_child, color_frame, accel_frame)
    return up_from_samples(np.array(samples, dtype=np.float64).reshape(-1, 3), rotation, str(path))
