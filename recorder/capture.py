"""What the recorder asks a RealSense device for and what it gets back, backend-independent.

`CaptureProfile` names the streams to open, `DeviceDescription` the device and calibration as
resolved, and `Capture` one unit of work for the writer (a colour/depth pair and IMU samples, as
numpy copies). A `Backend` delivers pyrealsense2 frames: `realsense_camera.RealSenseBackend` (a
camera) or `software_d455.SoftwareDeviceBackend` (a simulated D455, no hardware needed);
`frame_converter.FrameConverter` turns either's frames into Captures, so everything after the
backend is one code path. Nothing here imports pyrealsense2.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from octolog.kit.geometry import Intrinsics

VIDEO_STREAMS = ("color", "depth", "aligned_depth")
MOTION_STREAMS = ("gyro", "accel")


@dataclass(frozen=True)
class DeviceOptions:
    """Sensor options to set before streaming; None leaves the device's own value."""

    depth_units_m: float | None = None
    visual_preset: str | None = None
    emitter: str | None = None  # off, on, auto
    color_auto_exposure: bool | None = None
    depth_auto_exposure: bool | None = None
    color_exposure: float | None = None  # device units (D455 colour: 100 µs steps)
    depth_exposure: float | None = None  # device units (D455 depth: µs)


@dataclass(frozen=True)
class CaptureProfile:
    """The streams to open: sizes and rates, IMU rates (0: device default), options."""

    color: tuple[int, int, int] = (1280, 720, 30)  # width, height, fps
    depth: tuple[int, int, int] = (848, 480, 30)
    imu: bool = True
    gyro_fps: int = 0
    accel_fps: int = 0
    align: bool = True
    raw_depth: bool = False
    options: DeviceOptions = field(default_factory=DeviceOptions)


@dataclass
class DeviceDescription:
    """Device info and calibration as resolved when streaming starts; goes into the MCAP."""

    name: str
    serial: str
    firmware: str
    backend: str
    product_line: str = ""
    usb_type: str = ""
    depth_scale_m: float = 0.001
    color: Intrinsics | None = None
    depth: Intrinsics | None = None
    color_fps: int = 0
    depth_fps: int = 0
    gyro_fps: int = 0
    accel_fps: int = 0
    color_from_depth: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth_from_gyro: np.ndarray | None = None
    depth_from_accel: np.ndarray | None = None
    motion_intrinsics: dict[str, dict[str, list]] = field(default_factory=dict)
    options: dict[str, float] = field(default_factory=dict)
    distortion_models: dict[str, str] = field(default_factory=dict)
    groundtruth_tum: str = ""  # a simulated camera's true colour poses (TUM text; docs/formats.md)

    def metadata(self) -> dict[str, dict[str, str]]:
        """MCAP metadata records `device` and `calibration` (JSON values where structured), and
        `groundtruth` when the camera is a simulated one that knows its path."""

        def intr(i: Intrinsics | None, model: str) -> str:
            if i is None:
                return ""
            return json.dumps({"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx,
                               "cy": i.cy, "model": model, "coeffs": list(i.distortion)})

        def mat(m: np.ndarray | None) -> str:
            return "" if m is None else json.dumps(np.asarray(m).tolist())

        device = {"name": self.name, "serial": self.serial, "firmware": self.firmware, "backend": self.backend,
                  "product_line": self.product_line, "usb_type": self.usb_type,
                  "options": json.dumps(self.options, sort_keys=True)}
        cal = {"depth_scale_m": repr(self.depth_scale_m),
               "color_intrinsics": intr(self.color, self.distortion_models.get("color", "")),
               "depth_intrinsics": intr(self.depth, self.distortion_models.get("depth", "")),
               "color_fps": str(self.color_fps), "depth_fps": str(self.depth_fps),
               "gyro_fps": str(self.gyro_fps), "accel_fps": str(self.accel_fps),
               "color_from_depth": mat(self.color_from_depth),
               "depth_from_gyro": mat(self.depth_from_gyro), "depth_from_accel": mat(self.depth_from_accel),
               "imu_intrinsics": json.dumps(self.motion_intrinsics, sort_keys=True)}
        truth = {"groundtruth": {"tum": self.groundtruth_tum}} if self.groundtruth_tum else {}
        return {"device": device, "calibration": cal, **truth}


@dataclass(frozen=True)
class VideoFrame:
    stream: str  # color, depth or aligned_depth
    frame_number: int
    stamp_ns: int  # sensor time
    array: np.ndarray  # (H, W, 3) uint8 RGB, or (H, W) uint16 depth units


@dataclass(frozen=True)
class MotionSample:
    stream: str  # gyro (rad/s) or accel (m/s²)
    frame_number: int
    stamp_ns: int
    xyz: tuple[float, float, float]


@dataclass
class Capture:
    """One unit of work for the writer: a colour/depth pair (or what there is of it) and IMU samples.

    `seen` lists every device frame this unit accounts for, as (stream, frame number), whether or
    not it is recorded: frame-number gaps are drops at the device. `unpaired` names the streams
    that could not be produced (aligned depth without a colour partner).
    """

    color: VideoFrame | None = None
    depth: VideoFrame | None = None
    aligned_depth: VideoFrame | None = None
    motion: list[MotionSample] = field(default_factory=list)
    seen: list[tuple[str, int]] = field(default_factory=list)
    unpaired: list[str] = field(default_factory=list)

    def video(self) -> Iterator[VideoFrame]:
        for v in (self.color, self.aligned_depth, self.depth):
            if v is not None:
                yield v

    def streams(self) -> list[str]:
        """Recorded streams in this unit, one entry per sample."""
        return [v.stream for v in self.video()] + [m.stream for m in self.motion]

    @property
    def stamp_ns(self) -> int:
        """Colour time if any, else the first video or IMU sample's time."""
        for v in self.video():
            return v.stamp_ns
        return self.motion[0].stamp_ns if self.motion else 0

    @property
    def nbytes(self) -> int:
        return sum(v.array.nbytes for v in self.video()) + 40 * len(self.motion)


class Backend(Protocol):
    """A source of pyrealsense2 frames. `realtime`: frames arrive on their own clock (a camera), so
    a full writer queue must drop; otherwise the recorder may make the source wait."""

    realtime: bool

    def open(self, profile: CaptureProfile) -> DeviceDescription: ...

    def wait(self, timeout_s: float) -> list[Any] | None:
        """Frames or framesets available now ([] after the timeout); None when the source ended."""
        ...

    def close(self) -> None: ...


def blank_capture(device: DeviceDescription) -> Capture:
    """A tiny capture of every stream the device has (zeros), to warm up the writer's lazy set-up with."""
    def video(stream: str, shape: tuple[int, ...], dtype: type) -> VideoFrame:
        return VideoFrame(stream, 0, 0, np.zeros(shape, dtype))

    return Capture(color=video("color", (8, 8, 3), np.uint8) if device.color is not None else None,
                   depth=video("depth", (8, 8), np.uint16) if device.depth is not None else None,
                   aligned_depth=video("aligned_depth", (8, 8), np.uint16) if device.color is not None else None,
                   motion=[MotionSample(s, 0, 0, (0.0, 0.0, 0.0)) for s in MOTION_STREAMS])

