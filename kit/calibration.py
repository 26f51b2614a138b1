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

A TUM folder whose name does not say freiburg1/2/3, or an MCAP recording without CameraInfo, takes
one with `--set replay.camera=PATH.toml`. Any missing or invalid key is a one-line error naming it.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from octolog.kit import depthmodel
from octolog.kit.depthmodel import DepthModel
from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics


@dataclass(frozen=True)
class Calibration:
    name: str
    intrinsics: Intrinsics
    depth_scale_m: float | None  # None: the source's own
    readout_s: float
    depth_model: DepthModel | None = None  # None: the file does not say


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
                                  "readout_ms", *depthmodel.FIELDS})
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
    return Calibration(str(data.get("name", p.stem)), intrinsics, scale, readout, model)
