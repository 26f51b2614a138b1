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

A source without an accelerometer gives None. The run then keeps the old assumption (a camera held
level at the start, up = -y) and says so in `summary.json` and the status output.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from octolog.kit.errors import InputError

G = 9.80665
WINDOW_S = 0.1  # samples this close to the first frame are averaged
# a mean this far from g is no rest reading (the camera was accelerating, or the units are wrong)
MAX_G_ERROR = 0.25
# TUM's Kinect accelerometer axes in the colour camera's optical frame (see the module docstring)
KINECT_TO_OPTICAL = np.diag([-1.0, -1.0, 1.0])
# the simulated IMU: 200 Hz, white noise and a per-axis bias of a consumer MEMS accelerometer
SIM_RATE_HZ = 200.0
SIM_NOISE_MS2 = 0.02
SIM_BIAS_MS2 = 0.04


def up_from_samples(samples: np.ndarray, to_optical: np.ndarray, where: str) -> np.ndarray | None:
    """The mean of (N, 3) accelerometer samples as a unit up vector in the optical frame; None
    when there are none or their mean is not about g (not a rest reading)."""
    if samples.shape[0] == 0:
        return None
    mean = samples.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    if not np.isfinite(norm) or abs(norm - G) > MAX_G_ERROR * G:
        raise InputError(f"{where}: the accelerometer's mean near the first frame is {norm:.2f} m/s², "
                         f"not about g ({G:.2f}): wrong units, or the camera was not near rest; "
                         f"set mapper.grid_up to say which way is up")
    return to_optical @ (mean / norm)


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
