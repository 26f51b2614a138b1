"""A camera calibration file: what a source that does not say its camera needs, in one TOML file.

    # octolog camera calibration (replay.camera = "PATH.toml")
    name = "xtion-lab"        # how logs and the tracker name the camera
    width = 640
    height = 480
    fx = 525.0
    fy = 525.0
    cx = 319.5
    cy = 239.5
    distortion = [0.0, 0.0, 0.0, 0.0, 0.0]   # plumb-bob k1 k2 p1 p2 k3; optional
    depth_scale_m = 0.0002                    # metres per depth unit; optional (the source's own)
    readout_ms = 0.0                          # colour rolling-shutter readout; optional, 0 = global shutter
    depth_baseline_m = 0.075                  # the depth camera's error model (kit/depthmodel.py); optional:
    depth_focal_px = 580.0                    #   baseline, its own focal length (default fx) and
    depth_disparity_sigma_px = 0.062          #   disparity noise (one sigma), all or none
    camera_from_imu = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # the IMU on the colour
                                              #   camera (rows of a 4x4 rigid transform, metres); optional
    imu_time_offset_ms = 0.0                  # added to the IMU's stamps to put them on the camera's clock
    imu_gyro_noise = 2.44e-4                  # the IMU's noise (kit/imu.py: ImuNoise): densities and bias
    imu_accel_noise = 1.57e-3                 #   random walks, all or none (default: the D455's)
    imu_gyro_walk = 2.0e-5
    imu_accel_walk = 3.0e-4

A TUM folder whose name does not say freiburg1/2/3, or an MCAP recording without CameraInfo, takes
one with `--set replay.camera=PATH.toml`. Any missing or invalid key is a one-line error naming it.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octolog.kit import depthmodel
from octolog.kit.depthmodel import DepthModel
from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics
from octolog.kit.imu import IMU_NOISE_FIELDS, ImuNoise


@dataclass(frozen=True)
class Calibration:
    name: str
    intrinsics: Intrinsics
    depth_scale_m: float | None  # None: the source's own
    readout_s: float
    depth_model: DepthModel | None = None  # None: the file does not say
    camera_from_imu: np.ndarray | None = None  # (4, 4); None: the IMU's axes are the colour camera's
    imu_time_offset_s: float = 0.0  # added to the IMU's stamps
    imu_noise: ImuNoise | None = None  # None: the file does not say


def is_calibration_file(camera: str) -> bool:
    """Does `replay.camera` name a calibration file (rather than a TUM camera)?"""
    return camera.endswith(".toml")


def load_calibration(path: str | Path) -> Calibration:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise InputError(f"{p}: calibration file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: not a calibration file (invalid TOML: {exc})") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read the calibration file: {exc.strerror}") from None

    def number(key: str, *, default: float | None = None, positive: bool = True) -> float:
        value = data.get(key, default)
        if value is None:
            raise InputError(f"{p}: calibration key {key!r} missing")
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or \
                (value <= 0 if positive else value < 0):
            want = "positive" if positive else "non-negative"
            raise InputError(f"{p}: calibration key {key!r} = {value!r}: want a {want} number")
        return float(value)

    unknown = sorted(set(data) - {"name", "width", "height", "fx", "fy", "cx", "cy", "distortion", "depth_scale_m",
                                  "readout_ms", *depthmodel.FIELDS, "camera_from_imu", "imu_time_offset_ms",
                                  *IMU_NOISE_FIELDS})
    if unknown:
        raise InputError(f"{p}: unknown calibration key {unknown[0]!r}")
    distortion = data.get("distortion", [])
    if not isinstance(distortion, list) or len(distortion) not in (0, 4, 5, 8) or \
            not all(isinstance(k, int | float) and math.isfinite(k) for k in distortion):
        raise InputError(f"{p}: calibration key 'distortion' = {distortion!r}: want 0, 4, 5 or 8 numbers")
    width, height = number("width"), number("height")
    if width != int(width) or height != int(height):
        raise InputError(f"{p}: calibration width and height must be whole pixels")
    intrinsics = Intrinsics(int(width), int(height), number("fx"), number("fy"), number("cx", positive=False),
                            number("cy", positive=False), tuple(float(k) for k in distortion))
    scale = number("depth_scale_m") if "depth_scale_m" in data else None
    readout = number("readout_ms", default=0.0, positive=False) / 1e3
    if readout > 0.1:
        raise InputError(f"{p}: calibration key 'readout_ms' = {readout * 1e3:g}: want 0..100 ms")
    try:
        model = depthmodel.from_fields(data, focal_px=intrinsics.fx)
    except ValueError as exc:
        raise InputError(f"{p}: calibration key {exc}") from None
    given = [k for k in IMU_NOISE_FIELDS if k in data]
    if given and len(given) != len(IMU_NOISE_FIELDS):
        missing = next(k for k in IMU_NOISE_FIELDS if k not in data)
        raise InputError(f"{p}: calibration key {missing!r} missing (the IMU noise keys go together)")
    noise = ImuNoise(*(number(k) for k in IMU_NOISE_FIELDS)) if given else None
    offset = data.get("imu_time_offset_ms", 0.0)
    if isinstance(offset, bool) or not isinstance(offset, int | float) or not math.isfinite(offset) or abs(offset) > 1000:
        raise InputError(f"{p}: calibration key 'imu_time_offset_ms' = {offset!r}: want a number of ms, -1000 to 1000")
    return Calibration(str(data.get("name", p.stem)), intrinsics, scale, readout, model,
                       _rigid(data["camera_from_imu"], p) if "camera_from_imu" in data else None, offset / 1e3, noise)


def imu_keys(camera_from_imu: np.ndarray | None, time_offset_ms: float, noise: ImuNoise | None) -> str:
    """The IMU's keys of a calibration file (`load_calibration` reads them), for what a session
    measured of its IMU: the lines to put in the camera's calibration file."""
    lines = ["# The IMU as octolog's tracker measured it (summary.json `imu`): these keys go into the camera's",
             "# calibration file (replay.camera = \"PATH.toml\", docs/formats.md): the sessions that load it start from them."]
    if camera_from_imu is not None:
        rows = ", ".join("[" + ", ".join(f"{v:.9g}" for v in row) + "]" for row in np.asarray(camera_from_imu, float))
        lines.append(f"camera_from_imu = [{rows}]")
    lines.append(f"imu_time_offset_ms = {time_offset_ms + 0.0:.3f}")  # + 0.0: no "-0.000"
    if noise is not None:
        lines += [f"{key} = {value:.4g}" for key, value in zip(IMU_NOISE_FIELDS,
                  (noise.gyro_noise, noise.accel_noise, noise.gyro_walk, noise.accel_walk))]
    return "\n".join(lines) + "\n"


def _rigid(value: object, p: Path) -> np.ndarray:
    """A 4x4 rigid transform given as its rows."""
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        T = np.zeros(0)
    ok = T.shape == (4, 4) and np.isfinite(T).all() and np.allclose(T[3], [0, 0, 0, 1]) and \
        np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5) and np.linalg.det(T[:3, :3]) > 0
    if not ok:
        raise InputError(f"{p}: calibration key 'camera_from_imu': want the 4 rows of a rigid transform "
                         "(a rotation and a translation in metres)")
    return T
