"""Capture from a RealSense device: backends, profile checks, options, and frame conversion.

Two backends deliver the same pyrealsense2 frames: `RealSenseBackend` (a camera through a
pipeline) and `SoftwareDeviceBackend` (pyrealsense2's software device fed with a deterministic
synthetic scene at D455 profiles, so tests and benchmarks run without hardware). `FrameConverter`
turns either's frames into numpy samples (pairing colour with depth, aligning depth to colour),
so everything after the backend is one code path.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from octolog.kit.geometry import Intrinsics

VIDEO_STREAMS = ("color", "depth", "aligned_depth")
MOTION_STREAMS = ("gyro", "accel")
NO_DEVICE = ("no RealSense device found (is the camera plugged in, and does `rs-enumerate-devices` list it?)")

# What a D455 offers (librealsense 2.59, firmware 5.16): colour rgb8, depth z16, IMU by chip.
D455_COLOR = {(1280, 800): (5, 15, 30), (1280, 720): (5, 15, 30), (848, 480): (5, 15, 30, 60),
              (640, 480): (5, 15, 30, 60), (640, 360): (5, 15, 30, 60), (480, 270): (5, 15, 30, 60),
              (424, 240): (5, 15, 30, 60)}
D455_DEPTH = {(1280, 720): (5, 15, 30), (848, 480): (5, 15, 30, 60, 90), (640, 480): (5, 15, 30, 60, 90),
              (640, 360): (5, 15, 30, 60, 90), (480, 270): (5, 15, 30, 60, 90), (424, 240): (5, 15, 30, 60, 90),
              (256, 144): (90,)}
D455_IMU = {"bmi085": {"gyro": (200, 400), "accel": (100, 200)},
            "bmi055": {"gyro": (200, 400), "accel": (63, 250)}}


from octolog.kit.errors import DeviceLost, RecorderError  # noqa: E402  (re-exported for recorder modules)

# --- what the recorder asks for and what it gets ---------------------------------------------------


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

    def metadata(self) -> dict[str, dict[str, str]]:
        """MCAP metadata records `device` and `calibration` (JSON values where structured)."""
        import json

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
        return {"device": device, "calibration": cal}


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


# --- shared device logic -----------------------------------------------------------------------------


def stamp_ns(frame: Any) -> int:
    """A frame's sensor timestamp (librealsense milliseconds, a double) as integer nanoseconds."""
    return int(round(frame.get_timestamp() * 1e6))


def _f32(x: float) -> float:
    """A float32 from librealsense as the decimal it stands for (0.001, not 0.0010000000474974513)."""
    return float(str(np.float32(x)))


def _fps_list(rates: list[int]) -> str:
    return "/".join(str(r) for r in sorted(set(rates)))


def _supported_video(sensors: list[Any], stream: Any, fmt: Any) -> dict[tuple[int, int], list[int]]:
    out: dict[tuple[int, int], list[int]] = {}
    for s in sensors:
        for p in s.get_stream_profiles():
            if p.stream_type() == stream and p.format() == fmt and p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                out.setdefault((v.width(), v.height()), []).append(p.fps())
    return out


def _find_video(sensors: list[Any], stream: Any, fmt: Any, want: tuple[int, int, int], label: str,
                device: str) -> tuple[Any, Any]:
    for s in sensors:
        for p in s.get_stream_profiles():
            if p.stream_type() == stream and p.format() == fmt and p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                if (v.width(), v.height(), p.fps()) == want:
                    return s, v
    supported = _supported_video(sensors, stream, fmt)
    listing = ", ".join(f"{w}x{h}@{_fps_list(r)}" for (w, h), r in sorted(supported.items(), reverse=True))
    w, h, fps = want
    fmt_name = str(fmt).split(".")[-1]
    if not supported:
        raise RecorderError(f"{device} has no {label} stream in {fmt_name}")
    raise RecorderError(f"{label} {w}x{h}@{fps} is not supported by {device}; supported ({fmt_name}): {listing}")


def _find_motion(sensors: list[Any], stream: Any, fps: int, label: str, device: str) -> tuple[Any, Any] | None:
    cands = []
    for s in sensors:
        for p in s.get_stream_profiles():
            if p.stream_type() == stream and p.is_motion_stream_profile():
                cands.append((s, p))
    if not cands:
        return None
    if fps == 0:  # the device's default rate, else its lowest
        for s, p in cands:
            if p.is_default():
                return s, p.as_motion_stream_profile()
        s, p = min(cands, key=lambda sp: sp[1].fps())
        return s, p.as_motion_stream_profile()
    for s, p in cands:
        if p.fps() == fps:
            return s, p.as_motion_stream_profile()
    raise RecorderError(f"{label} at {fps} Hz is not supported by {device}; supported: "
                        f"{_fps_list([p.fps() for _, p in cands])} Hz")


def _matrix(ext: Any) -> np.ndarray:
    """librealsense extrinsics (column-major rotation) as a 4x4 `to_from_from` matrix."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(ext.rotation, dtype=np.float64).reshape(3, 3).T
    T[:3, 3] = ext.translation
    return T


def _intrinsics(vp: Any) -> tuple[Intrinsics, str]:
    i = vp.get_intrinsics()
    model = str(i.model).split(".")[-1]
    coeffs = tuple(float(c) for c in i.coeffs)
    return Intrinsics(i.width, i.height, float(i.fx), float(i.fy), float(i.ppx), float(i.ppy),
                      coeffs if any(coeffs) or model != "none" else ()), model


@dataclass
class Resolved:
    """Sensor profiles chosen for a CaptureProfile, per stream, with the sensors that own them."""

    profiles: dict[str, tuple[Any, Any]] = field(default_factory=dict)  # stream -> (sensor, profile)

    def by_sensor(self) -> list[tuple[Any, list[Any]]]:
        out: list[tuple[Any, list[Any]]] = []
        for sensor, profile in self.profiles.values():
            for s, ps in out:
                if s == sensor:
                    ps.append(profile)
                    break
            else:
                out.append((sensor, [profile]))
        return out


def resolve(device: Any, profile: CaptureProfile) -> Resolved:
    """Find the requested profiles among the device's; a missing one raises naming what is supported."""
    import pyrealsense2 as rs

    name = device.get_info(rs.camera_info.name) if device.supports(rs.camera_info.name) else "the device"
    sensors = list(device.query_sensors())
    res = Resolved()
    res.profiles["color"] = _find_video(sensors, rs.stream.color, rs.format.rgb8, profile.color, "colour", name)
    res.profiles["depth"] = _find_video(sensors, rs.stream.depth, rs.format.z16, profile.depth, "depth", name)
    if profile.imu:
        for label, stream, fps in (("gyro", rs.stream.gyro, profile.gyro_fps),
                                   ("accel", rs.stream.accel, profile.accel_fps)):
            found = _find_motion(sensors, stream, fps, label, name)
            if found is None:
                raise RecorderError(f"{name} has no {label} stream (an IMU-less model?); record with --no-imu")
            res.profiles[label] = found
    return res


_OPTION_NAMES = {"depth_units_m": "depth_units", "emitter": "emitter_enabled", "visual_preset": "visual_preset",
                 "color_auto_exposure": "enable_auto_exposure", "depth_auto_exposure": "enable_auto_exposure",
                 "color_exposure": "exposure", "depth_exposure": "exposure"}
_EMITTER = {"off": 0.0, "on": 1.0, "auto": 2.0}


def apply_options(res: Resolved, opts: DeviceOptions) -> dict[str, float]:
    """Set the requested options on the depth and colour sensors; the values in force afterwards."""
    import pyrealsense2 as rs

    depth_sensor = res.profiles["depth"][0]
    color_sensor = res.profiles["color"][0]
    wanted: list[tuple[str, Any, Any, float]] = []  # key, sensor, option, value
    if opts.depth_units_m is not None:
        wanted.append(("depth_units_m", depth_sensor, rs.option.depth_units, opts.depth_units_m))
    if opts.visual_preset is not None:
        presets = rs.rs400_visual_preset.__members__
        if opts.visual_preset not in presets:
            raise RecorderError(f"visual preset {opts.visual_preset!r}: want one of {', '.join(presets)}")
        wanted.append(("visual_preset", depth_sensor, rs.option.visual_preset,
                       float(int(presets[opts.visual_preset]))))
    if opts.emitter is not None:
        wanted.append(("emitter", depth_sensor, rs.option.emitter_enabled, _EMITTER[opts.emitter]))
    if opts.depth_auto_exposure is not None:
        wanted.append(("depth_auto_exposure", depth_sensor, rs.option.enable_auto_exposure,
                       float(opts.depth_auto_exposure)))
    if opts.depth_exposure is not None:
        wanted.append(("depth_exposure", depth_sensor, rs.option.exposure, opts.depth_exposure))
    if opts.color_auto_exposure is not None:
        wanted.append(("color_auto_exposure", color_sensor, rs.option.enable_auto_exposure,
                       float(opts.color_auto_exposure)))
    if opts.color_exposure is not None:
        wanted.append(("color_exposure", color_sensor, rs.option.exposure, opts.color_exposure))
    for key, sensor, option, value in wanted:
        if not sensor.supports(option):
            raise RecorderError(f"option {key}: not supported by the {sensor.get_info(rs.camera_info.name)}")
        if abs(float(sensor.get_option(option)) - value) <= 1e-6 * max(1.0, abs(value)):
            continue  # already so (float options refuse to be set to their own value on some sensors)
        r = sensor.get_option_range(option)
        if not r.min <= value <= r.max:
            raise RecorderError(f"option {key}={value:g}: outside the device's range {r.min:g}..{r.max:g}")
        try:
            sensor.set_option(option, value)
        except RuntimeError as exc:
            raise RecorderError(f"option {key}={value:g}: the device refused it ({exc})") from None
    now: dict[str, float] = {}
    for key, sensor in (("depth_units_m", depth_sensor), ("visual_preset", depth_sensor),
                        ("emitter", depth_sensor), ("depth_auto_exposure", depth_sensor),
                        ("depth_exposure", depth_sensor), ("color_auto_exposure", color_sensor),
                        ("color_exposure", color_sensor)):
        option = getattr(rs.option, _OPTION_NAMES[key])
        if sensor.supports(option):
            try:
                now[key] = _f32(sensor.get_option(option))
            except RuntimeError:
                pass
    return now


def describe(device: Any, res: Resolved, backend: str, options: dict[str, float]) -> DeviceDescription:
    """Device info and calibration of the resolved profiles."""
    import pyrealsense2 as rs

    def info(key: Any) -> str:
        return device.get_info(key) if device.supports(key) else ""

    _, cp = res.profiles["color"]
    dsensor, dp = res.profiles["depth"]
    color, cmodel = _intrinsics(cp)
    depth, dmodel = _intrinsics(dp)
    try:
        scale = dsensor.as_depth_sensor().get_depth_scale()
    except RuntimeError:
        scale = dsensor.get_option(rs.option.depth_units)
    scale = _f32(scale)
    desc = DeviceDescription(
        name=info(rs.camera_info.name), serial=info(rs.camera_info.serial_number),
        firmware=info(rs.camera_info.firmware_version), backend=backend,
        product_line=info(rs.camera_info.product_line), usb_type=info(rs.camera_info.usb_type_descriptor),
        depth_scale_m=scale, color=color, depth=depth, color_fps=cp.fps(), depth_fps=dp.fps(),
        color_from_depth=_matrix(dp.get_extrinsics_to(cp)), options=options,
        distortion_models={"color": cmodel, "depth": dmodel})
    for label in MOTION_STREAMS:
        if label not in res.profiles:
            continue
        _, mp = res.profiles[label]
        setattr(desc, f"{label}_fps", mp.fps())
        try:
            setattr(desc, f"depth_from_{label}", _matrix(mp.get_extrinsics_to(dp)))
        except RuntimeError:
            pass
        try:
            mi = mp.get_motion_intrinsics()
            desc.motion_intrinsics[label] = {"data": np.asarray(mi.data, dtype=float).tolist(),
                                             "noise_variances": [float(x) for x in mi.noise_variances],
                                             "bias_variances": [float(x) for x in mi.bias_variances]}
        except RuntimeError:
            pass  # not calibrated on this unit
    return desc


# --- frames -> samples ----------------------------------------------------------------------------


class FrameConverter:
    """pyrealsense2 frames/framesets -> Captures (numpy copies, so device buffers go back at once).

    Colour and depth of one instant form a pair; a pair is aligned (depth registered to colour)
    when asked. librealsense's syncer sometimes hands the two over separately (at start-up, or
    when one is late): a lone frame is held until its partner arrives (same time within half a
    frame period) and paired then; if none comes, it goes out alone and the aligned depth it
    could not make is reported as unpaired.
    """

    def __init__(self, *, align: bool, raw_depth: bool, fps: int) -> None:
        import pyrealsense2 as rs

        self._rs = rs
        self.align = align
        self.raw_depth = raw_depth
        self._tol_ns = 500_000_000 // max(fps, 1)
        self._aligner = rs.align(rs.stream.color) if align else None
        self._pending: Any = None
        self._partner: Any = None
        self._composed = rs.frame_queue(2, keep_frames=True)
        self._composer = rs.processing_block(self._compose)
        self._composer.start(self._composed)

    def _compose(self, frame: Any, source: Any) -> None:
        source.frame_ready(source.allocate_composite_frame([frame, self._partner]))

    def convert(self, item: Any) -> list[Capture]:
        rs = self._rs
        frames = list(item.as_frameset()) if item.is_frameset() else [item]
        color = depth = None
        motion: list[MotionSample] = []
        seen: list[tuple[str, int]] = []
        for f in frames:
            st = f.get_profile().stream_type()
            if st == rs.stream.color:
                color = f
            elif st == rs.stream.depth:
                depth = f
            elif st in (rs.stream.gyro, rs.stream.accel):
                d = f.as_motion_frame().get_motion_data()
                name = "gyro" if st == rs.stream.gyro else "accel"
                motion.append(MotionSample(name, int(f.get_frame_number()), stamp_ns(f),
                                           (float(d.x), float(d.y), float(d.z))))
                seen.append((name, int(f.get_frame_number())))
        out: list[Capture] = []
        if color is not None and depth is not None:
            out += self.flush()
            out.append(self._pair(color, depth, item if item.is_frameset() else None))
        elif color is not None or depth is not None:
            lone = color if color is not None else depth
            p = self._pending
            if p is not None and p.get_profile().stream_type() != lone.get_profile().stream_type() \
                    and abs(stamp_ns(p) - stamp_ns(lone)) <= self._tol_ns:
                self._pending = None
                c, d = (lone, p) if lone is color else (p, lone)
                out.append(self._pair(c, d, None))
            else:
                out += self.flush()
                self._pending = lone
        if motion:
            out.append(Capture(motion=motion, seen=seen))
        return out

    def flush(self) -> list[Capture]:
        """The held lone frame, if any, as a Capture of its own."""
        if self._pending is None:
            return []
        f, self._pending = self._pending, None
        if f.get_profile().stream_type() == self._rs.stream.color:
            return [Capture(color=self._video("color", f), seen=[("color", int(f.get_frame_number()))],
                            unpaired=["aligned_depth"] if self.align else [])]
        cap = Capture(seen=[("depth", int(f.get_frame_number()))], unpaired=["aligned_depth"] if self.align else [])
        if self.raw_depth:
            cap.depth = self._video("depth", f)
        return [cap]

    def _pair(self, color: Any, depth: Any, frameset: Any) -> Capture:
        cap = Capture(color=self._video("color", color),
                      seen=[("color", int(color.get_frame_number())), ("depth", int(depth.get_frame_number()))])
        if self.raw_depth:
            cap.depth = self._video("depth", depth)
        if self._aligner is not None:
            if frameset is None:
                self._partner = depth
                self._composer.invoke(color)
                frameset = self._composed.wait_for_frame(1000).as_frameset()
                self._partner = None
            aligned = self._aligner.process(frameset).get_depth_frame()
            # the aligned image is depth measured at the depth frame's time, in colour's geometry
            cap.aligned_depth = self._video("aligned_depth", aligned)
        return cap

    @staticmethod
    def _video(stream: str, f: Any) -> VideoFrame:
        arr = np.asanyarray(f.get_data()).copy()
        return VideoFrame(stream, int(f.get_frame_number()), stamp_ns(f), arr)


# --- a real camera -----------------------------------------------------------------------------------


class RealSenseBackend:
    """A RealSense camera through a pyrealsense2 pipeline; frames queue in librealsense (64 deep)
    and go to the recorder as they come. No frames for `stall_s` means the camera is gone."""

    realtime = True

    def __init__(self, serial: str = "", *, stall_s: float = 3.0) -> None:
        self.serial = serial
        self.stall_s = stall_s
        self._pipeline: Any = None
        self._queue: Any = None
        self._last = 0.0

    def open(self, profile: CaptureProfile) -> DeviceDescription:
        import pyrealsense2 as rs

        devices = list(rs.context().query_devices())
        if not devices:
            raise RecorderError(NO_DEVICE)
        serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
        if self.serial and self.serial not in serials:
            raise RecorderError(f"no RealSense device with serial {self.serial} (attached: {', '.join(serials)})")
        device = devices[serials.index(self.serial)] if self.serial else devices[0]
        self.serial = device.get_info(rs.camera_info.serial_number)
        res = resolve(device, profile)
        options = apply_options(res, profile.options)
        cfg = rs.config()
        cfg.enable_device(self.serial)
        for stream, (_, p) in res.profiles.items():
            if p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                cfg.enable_stream(p.stream_type(), v.width(), v.height(), p.format(), p.fps())
            else:
                cfg.enable_stream(p.stream_type(), p.format(), p.fps())
        self._queue = rs.frame_queue(64, keep_frames=True)
        self._pipeline = rs.pipeline()
        try:
            self._pipeline.start(cfg, self._queue.enqueue)
        except RuntimeError as exc:
            raise RecorderError(f"cannot start streaming from {self.serial}: {exc}") from None
        self._last = time.monotonic()
        return describe(device, res, "realsense", options)

    def wait(self, timeout_s: float) -> list[Any] | None:
        import pyrealsense2 as rs

        ok, frame = self._queue.try_wait_for_frame(int(timeout_s * 1000))
        if not ok:
            if time.monotonic() - self._last > self.stall_s:
                attached = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
                if self.serial not in attached:
                    raise DeviceLost(f"camera {self.serial} disconnected")
                raise DeviceLost(f"camera {self.serial} sent no frames for {self.stall_s:.0f} s")
            return []
        self._last = time.monotonic()
        out = [frame]
        while (more := self._queue.poll_for_frame()):
            out.append(more)
        return out

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass  # already gone with the device
            self._pipeline = None


# --- the software device -----------------------------------------------------------------------------


class SyntheticScene:
    """Deterministic image content: a textured, moving colour pattern and a bumpy depth surface.

    Frames are windows into larger precomputed images (cheap to cut, so the source costs little
    next to the recorder), shifted a little each frame; fixed-seed noise makes the compression
    figures closer to a real sensor's than flat test patterns would.
    """

    PAD = 96

    def __init__(self, color_wh: tuple[int, int], depth_wh: tuple[int, int], *, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        cw, ch = color_wh
        H, W = ch + self.PAD, cw + self.PAD
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        checker = ((xx // 40 + yy // 40) % 2) * 60
        base = np.stack([128 + 90 * np.sin(xx / 97.0) + checker, 128 + 90 * np.cos(yy / 61.0),
                         128 + 60 * np.sin((xx + yy) / 45.0) - checker / 2], axis=-1)
        base += rng.normal(0, 3.0, base.shape)
        self._color = np.clip(base, 0, 255).astype(np.uint8)
        dw, dh = depth_wh
        H, W = dh + self.PAD, dw + self.PAD
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        surf = 1500 + 2.0 * yy + 300 * np.sin(xx / 53.0) * np.cos(yy / 37.0) + rng.normal(0, 2.0, (H, W))
        depth = np.clip(surf, 0, 65535).astype(np.uint16)
        depth[(rng.random((H, W)) < 0.02) | ((xx // 64 + yy // 48) % 11 == 0)] = 0  # holes
        self._depth = depth
        self._cwh, self._dwh = color_wh, depth_wh

    def _window(self, img: np.ndarray, wh: tuple[int, int], i: int) -> np.ndarray:
        dx, dy = (3 * i) % self.PAD, (2 * i) % self.PAD
        return np.ascontiguousarray(img[dy:dy + wh[1], dx:dx + wh[0]])

    def color(self, i: int) -> np.ndarray:
        return self._window(self._color, self._cwh, i)

    def depth(self, i: int) -> np.ndarray:
        return self._window(self._depth, self._dwh, i)

    @staticmethod
    def motion(stream: str, k: int) -> tuple[float, float, float]:
        """IMU values as float32 would hold them (the frames carry float32)."""
        if stream == "gyro":
            v = (0.02 * np.sin(k / 50.0), 0.03 * np.cos(k / 70.0), 0.005 + 0.001 * np.sin(k / 9.0))
        else:
            v = (0.3 * np.sin(k / 40.0), -9.81 + 0.05 * np.cos(k / 30.0), 0.2 * np.sin(k / 17.0))
        return tuple(float(np.float32(x)) for x in v)  # type: ignore[return-value]


@dataclass(frozen=True)
class Pushed:
    stream: str
    frame_number: int
    stamp_ns: int


class SoftwareDeviceBackend:
    """pyrealsense2's software device posing as a D455: every D455 colour/depth profile and the
    IMU rates of the chosen chip, D455-like calibration and options. Frames of the synthetic
    scene are pushed into the sensors and come back through `rs.syncer` as real rs frames.

    On demand (default) a frame pair and the IMU samples up to the next frame time are pushed
    each time the recorder asks, so sensor time runs as fast as the recorder takes frames;
    `paced` pushes on the sensor clock in wall time, like a camera. `frames` ends the stream
    after that many pairs; `unplug_after` raises DeviceLost after that many, like a pulled cable.
    `pushed` logs what went in, for tests.
    """

    START_NS = 1_000_000_000  # sensor clock at the first frame
    MAX_LAG_S = 0.25

    def __init__(self, *, frames: int = 0, paced: bool = False, unplug_after: int = 0, imu_chip: str = "bmi085",
                 seed: int = 0, serial: str = "SW-D455-0001") -> None:
        self.frames = frames
        self.paced = paced
        self.realtime = paced
        self.unplug_after = unplug_after
        self.imu_chip = imu_chip
        self.seed = seed
        self.serial = serial
        self.pushed: list[Pushed] = []
        self.skipped: list[Pushed] = []  # paced: samples lost because the recorder was late
        self.scene: SyntheticScene | None = None
        self._i = 0
        self._k = {"gyro": 0, "accel": 0}
        self._t0 = 0.0
        self._started: list[Any] = []
        self._done = False

    # building the device

    def _build(self) -> None:
        import pyrealsense2 as rs

        self._rs = rs
        dev = rs.software_device()
        dev.register_info(rs.camera_info.name, "Intel RealSense D455 (software device)")
        dev.register_info(rs.camera_info.serial_number, self.serial)
        dev.register_info(rs.camera_info.firmware_version, "5.16.0.1")
        dev.register_info(rs.camera_info.product_line, "D400")
        self._depth_s = dev.add_sensor("Stereo Module")
        self._color_s = dev.add_sensor("RGB Camera")
        self._motion_s = dev.add_sensor("Motion Module")
        uid = iter(range(1, 10_000))
        self._dprof: dict[tuple[int, int, int], Any] = {}
        self._cprof: dict[tuple[int, int, int], Any] = {}
        self._mprof: dict[tuple[str, int], Any] = {}
        for table, sensor, stream, fmt, bpp, fov, store, default in (
                (D455_DEPTH, self._depth_s, rs.stream.depth, rs.format.z16, 2, 87.0, self._dprof, (848, 480, 30)),
                (D455_COLOR, self._color_s, rs.stream.color, rs.format.rgb8, 3, 90.0, self._cprof,
                 (1280, 720, 30))):
            for (w, h), rates in table.items():
                for fps in rates:
                    vs = rs.video_stream()
                    vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps = stream, 0, next(uid), w, h, fps
                    vs.bpp, vs.fmt = bpp, fmt
                    intr = rs.intrinsics()
                    f = w / 2 / np.tan(np.radians(fov / 2))
                    intr.width, intr.height, intr.fx, intr.fy = w, h, f, f
                    intr.ppx, intr.ppy = w / 2 - 0.5 + 1.25, h / 2 - 0.5 - 0.75
                    intr.model = rs.distortion.brown_conrady
                    intr.coeffs = [0.0] * 5
                    vs.intrinsics = intr
                    store[(w, h, fps)] = sensor.add_video_stream(vs, (w, h, fps) == default)
        for stream_name, stream in (("gyro", rs.stream.gyro), ("accel", rs.stream.accel)):
            for n, fps in enumerate(D455_IMU[self.imu_chip][stream_name]):
                ms = rs.motion_stream()
                ms.type, ms.index, ms.uid, ms.fps, ms.fmt = stream, 0, next(uid), fps, rs.format.motion_xyz32f
                mi = rs.motion_device_intrinsic()
                mi.data = [[1.0, 0.0, 0.0, 0.001], [0.0, 1.0, 0.0, -0.002], [0.0, 0.0, 1.0, 0.0005]]
                mi.noise_variances = [1e-5, 1e-5, 1e-5] if stream_name == "gyro" else [1e-3, 1e-3, 1e-3]
                mi.bias_variances = [1e-7, 1e-7, 1e-7] if stream_name == "gyro" else [1e-5, 1e-5, 1e-5]
                ms.intrinsics = mi
                self._mprof[(stream_name, fps)] = self._motion_s.add_motion_stream(ms, n == 0)
        # calibration: colour 59 mm beside the left imager, IMU a little behind it (D455-like)
        to_color = rs.extrinsics()
        to_color.rotation = [0.99999, 0.00436, -0.00100, -0.00436, 0.99999, 0.00050, 0.00100, -0.00050, 1.0]
        to_color.translation = [-0.059, 0.0001, 0.0003]
        to_imu = rs.extrinsics()
        to_imu.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        to_imu.translation = [-0.03022, 0.0074, 0.01602]
        for dp in self._dprof.values():
            for cp in self._cprof.values():
                dp.register_extrinsics_to(cp, to_color)
            for mp in self._mprof.values():
                dp.register_extrinsics_to(mp, to_imu)
        # options as a D455 has them (ranges and defaults)
        opt = rs.option
        for sensor, option, lo, hi, step, default in (
                (self._depth_s, opt.depth_units, 1e-6, 0.01, 1e-6, 0.001),
                (self._depth_s, opt.visual_preset, 0, 5, 1, 0),
                (self._depth_s, opt.emitter_enabled, 0, 2, 1, 1),
                (self._depth_s, opt.enable_auto_exposure, 0, 1, 1, 1),
                (self._depth_s, opt.exposure, 1, 200000, 1, 33000),
                (self._color_s, opt.enable_auto_exposure, 0, 1, 1, 1),
                (self._color_s, opt.exposure, 1, 10000, 1, 156)):
            # pyrealsense2 2.59's option_range(a, b, c, d) takes (min, max, default, step), whatever
            # its docstring says
            sensor.add_option(option, rs.option_range(lo, hi, default, step), True)
        self._dev = dev

    # Backend

    def open(self, profile: CaptureProfile) -> DeviceDescription:
        import pyrealsense2 as rs

        self._build()
        res = resolve(self._dev, profile)
        options = apply_options(res, profile.options)
        self._profile = profile
        self._units = float(self._depth_s.get_option(rs.option.depth_units))
        self._res = res
        # colour and depth through a syncer (pairs by timestamp, as in a pipeline); the IMU into a
        # plain queue: a syncer holds IMU samples back for matching and keeps the last ones
        self._sync = rs.syncer(256)
        self._motion_q = rs.frame_queue(1024, keep_frames=True)
        for sensor, profiles in res.by_sensor():
            sensor.open(profiles)
            sensor.start(self._motion_q if sensor == self._motion_s else self._sync)
            self._started.append(sensor)
        _, cp = res.profiles["color"]
        _, dp = res.profiles["depth"]
        self._fps = cp.fps()
        self.scene = SyntheticScene(profile.color[:2], profile.depth[:2], seed=self.seed)
        self._t0 = time.monotonic()
        return describe(self._dev, res, "software", options)

    def stamp_of(self, stream: str, n: int) -> int:
        """Sensor time of the n-th pushed sample of a stream (integer ns on the device clock)."""
        fps = self._res.profiles[stream][1].fps() if stream in MOTION_STREAMS else self._fps
        return self.START_NS + n * 1_000_000_000 // fps

    def wait(self, timeout_s: float) -> list[Any] | None:
        if self._done:
            return None
        video_next = self._next_stamp() == self.stamp_of("color", self._i)
        if video_next and self.frames and self._i >= self.frames:
            self._done = True
            return self._drain() or None
        if video_next and self.unplug_after and self._i >= self.unplug_after:
            self._done = True
            raise DeviceLost(f"camera {self.serial} disconnected (software device unplugged after {self._i} frames)")
        if self.paced:
            self._skip_late()
            due = self._t0 + (self._next_stamp() - self.START_NS) / 1e9 - time.monotonic()
            if due > timeout_s:
                time.sleep(timeout_s)
                return []
            if due > 0:
                time.sleep(due)  # pacing the simulated sensor clock, not synchronisation
        self._push_step()
        return self._drain()

    def _skip_late(self) -> None:
        """Paced: samples due more than MAX_LAG_S ago are lost, as a camera's would be when
        nobody takes them (librealsense's queues are bounded): frame-number gaps."""
        late = time.monotonic() - self._t0 - self.MAX_LAG_S
        while (self._next_stamp() - self.START_NS) / 1e9 < late:
            t = self._next_stamp()
            if t == self.stamp_of("color", self._i):
                if self.frames and self._i >= self.frames:
                    return
                self.skipped.append(Pushed("color", self._i, t))
                self._i += 1
            else:
                st = min(MOTION_STREAMS, key=lambda s: (self.stamp_of(s, self._k[s]), s))
                self.skipped.append(Pushed(st, self._k[st], t))
                self._k[st] += 1

    def _next_stamp(self) -> int:
        t = self.stamp_of("color", self._i)
        if self._profile.imu:
            t = min([t] + [self.stamp_of(st, self._k[st]) for st in MOTION_STREAMS])
        return t

    def _drain(self) -> list[Any]:
        out = []
        while (fs := self._sync.poll_for_frames()):
            out.append(fs)
        while (f := self._motion_q.poll_for_frame()):
            out.append(f)
        return out

    def _push_step(self) -> None:
        """Push the next sample in sensor-time order: the next frame pair, or one IMU sample.

        One at a time, drained at once: librealsense's frame pool for a software sensor is small,
        and frames pushed while many are still held are lost without a word.
        """
        rs = self._rs
        t_video = self.stamp_of("color", self._i)
        if self._profile.imu:
            stream = min(MOTION_STREAMS, key=lambda st: (self.stamp_of(st, self._k[st]), st))
            ts = self.stamp_of(stream, self._k[stream])
            if ts < t_video:
                k = self._k[stream]
                x, y, z = SyntheticScene.motion(stream, k)
                v = rs.vector()
                v.x, v.y, v.z = x, y, z
                f = rs.software_motion_frame()
                f.data = v
                f.timestamp = ts / 1e6
                f.domain = rs.timestamp_domain.hardware_clock
                f.frame_number = k
                f.profile = self._res.profiles[stream][1]
                self._motion_s.on_motion_frame(f)
                self.pushed.append(Pushed(stream, k, ts))
                self._k[stream] += 1
                return
        i = self._i
        assert self.scene is not None
        for sensor, key, arr, bpp in ((self._color_s, "color", self.scene.color(i), 3),
                                      (self._depth_s, "depth", self.scene.depth(i), 2)):
            f = rs.software_video_frame()
            f.pixels = arr
            f.bpp = bpp
            f.stride = arr.shape[1] * bpp
            f.timestamp = t_video / 1e6
            f.domain = rs.timestamp_domain.hardware_clock
            f.frame_number = i
            f.profile = self._res.profiles[key][1]
            if key == "depth":
                f.depth_units = self._units
            sensor.on_video_frame(f)
            self.pushed.append(Pushed(key, i, t_video))
        self._i += 1

    def close(self) -> None:
        for sensor in self._started:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:
                pass
        self._started.clear()
