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
of the accelerometer's up (a floor, a table), its normal is taken instead (`octolog.kit.up_vector.level_on_plane`).

A source without an accelerometer gives None. The run then keeps the old assumption (a camera held
level at the start, up = -y) and says so in `summary.json` and the status output.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import RgbdFrame
from octolog.kit.up_vector import WINDOW_S, G, level_on_plane, rotation_between, up_from_samples
from octolog.kit.mcaplog import read_messages
from octolog.schemas import codec, posemsgs
from octolog.schemas.topics import ACCEL, TF_STATIC

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


class UpSource(Protocol):
    """What `source_up` needs of a replay source (octolog.replay.sources.Source)."""

    def gravity_up(self) -> np.ndarray | None: ...

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]: ...


def source_up(source: UpSource) -> tuple[np.ndarray, str] | None:
    """(up, note) at a file source's first frame: its accelerometer, levelled on frame 0's plane
    when there is one; None without an accelerometer. What `octolog run` gives the mapper as
    `grid_up`, and what the replay publishes on `camera/gravity` for a mapper elsewhere."""
    up = source.gravity_up()
    if up is None:
        return None
    up, levelled = level_on_plane(up, next(iter(source.frames(0, 1))))
    return up, "gravity-aligned (accelerometer" + (", levelled on a horizontal plane of frame 0)" if levelled else ")")


def recorded_up(path: Path, first_stamp_ns: int, color_frame: str) -> np.ndarray | None:
    """Up at a recording's first colour frame from its `camera/accel/sample` (sensor_msgs/Imu, the
    realsense-ros topic `octolog record` writes), rotated into the colour camera's optical frame by
    the file's `/tf_static` (None without accelerometer samples near that frame). Without a
    transform from the accelerometer's frame to the colour frame, the two are taken as aligned:
    RealSense IMU optical frames share the cameras' axes."""
    samples, accel_frame, parent_from_child = [], "", {}
    for m in read_messages(path, [ACCEL.name, TF_STATIC.name]):
        msg = codec.decode(m.data, TF_STATIC.msgtype if m.topic == TF_STATIC.name else ACCEL.msgtype)
        if m.topic == TF_STATIC.name:
            for parent, child, T in posemsgs.tf_transforms(msg):
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
