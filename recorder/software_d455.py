"""A software D455: pyrealsense2's software device posing as the camera, so the recorder runs end to
end without hardware.

What it films comes from a `FrameProvider`, made for the streams the device opens (`SimulatedLayout`:
intrinsics, rates, depth units, the depth imager's and the IMU's place on the colour camera): by
default `SyntheticPattern`, flat pictures and sine waves, cheap (the recorder's own tests and
benchmarks); the shell gives it a rendered 3D scene with a known trajectory instead
(shell/simcamera.py), whose ground truth the recording then carries."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import pyrealsense2 as rs

from octolog.kit.errors import DeviceLost
from octolog.kit.geometry import Intrinsics
from octolog.recorder.capture import MOTION_STREAMS, CaptureProfile, DeviceDescription
from octolog.recorder.device_profiles import apply_options, describe, resolve

# What a D455 offers (librealsense 2.59, firmware 5.16): colour rgb8, depth z16, IMU by chip.
D455_COLOR = {(1280, 800): (5, 15, 30), (1280, 720): (5, 15, 30), (848, 480): (5, 15, 30, 60),
              (640, 480): (5, 15, 30, 60), (640, 360): (5, 15, 30, 60), (480, 270): (5, 15, 30, 60),
              (424, 240): (5, 15, 30, 60)}
D455_DEPTH = {(1280, 720): (5, 15, 30), (848, 480): (5, 15, 30, 60, 90), (640, 480): (5, 15, 30, 60, 90),
              (640, 360): (5, 15, 30, 60, 90), (480, 270): (5, 15, 30, 60, 90), (424, 240): (5, 15, 30, 60, 90),
              (256, 144): (90,)}
D455_IMU = {"bmi085": {"gyro": (200, 400), "accel": (100, 200)},
            "bmi055": {"gyro": (200, 400), "accel": (63, 250)}}
DEPTH_FOV_DEG, COLOR_FOV_DEG = 87.0, 90.0  # horizontal; pinhole intrinsics from these (`video_intrinsics`)
# calibration (D455-like): colour 59 mm beside the left imager, the IMU a little behind it. As
# librealsense takes them: rotation column-major, p_to = R p_from + t
DEPTH_TO_COLOR = ((0.99999, 0.00436, -0.00100, -0.00436, 0.99999, 0.00050, 0.00100, -0.00050, 1.0),
                  (-0.059, 0.0001, 0.0003))
DEPTH_TO_IMU = ((1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), (-0.03022, 0.0074, 0.01602))
START_NS = 1_000_000_000  # sensor clock at the first frame


def video_intrinsics(w: int, h: int, fov_deg: float) -> Intrinsics:
    """A software D455 stream's pinhole intrinsics: square pixels from the horizontal field of
    view, the principal point a little off centre."""
    f = w / 2 / np.tan(np.radians(fov_deg / 2))
    return Intrinsics(w, h, float(f), float(f), w / 2 - 0.5 + 1.25, h / 2 - 0.5 - 0.75, (0.0,) * 5)


def to_from(extrinsics: tuple[tuple[float, ...], tuple[float, ...]]) -> np.ndarray:
    """librealsense extrinsics (column-major rotation, translation) as a 4x4 `to_from_from`."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(extrinsics[0], dtype=np.float64).reshape(3, 3).T
    T[:3, 3] = extrinsics[1]
    return T


def stamp_ns(rate: int, n: int) -> int:
    """Sensor time of the n-th sample of a stream at `rate` Hz (integer ns on the device clock)."""
    return START_NS + n * 1_000_000_000 // rate


@dataclass(frozen=True)
class SimulatedLayout:
    """What a frame provider must produce for the streams the software D455 opened: colour
    (`color` intrinsics) and depth (`depth` intrinsics, seen from the depth imager, in
    `depth_units_m`) at `fps`, frame i at `stamp_ns(fps, i)`; gyro and accelerometer samples at
    their rates (0: no IMU), in the IMU's frame (`color_from_depth @ depth_from_imu` places it)."""

    color: Intrinsics
    depth: Intrinsics
    fps: int
    gyro_hz: int
    accel_hz: int
    depth_units_m: float
    color_from_depth: tuple[tuple[float, ...], ...]  # 4x4, row-major (hashable)
    depth_from_imu: tuple[tuple[float, ...], ...]

    @property
    def color_from_imu(self) -> np.ndarray:
        return np.asarray(self.color_from_depth) @ np.asarray(self.depth_from_imu)


def simulated_layout(profile: CaptureProfile, gyro_hz: int, accel_hz: int) -> SimulatedLayout:
    """The layout of a profile, with the IMU rates it resolves to (0: no IMU)."""
    (cw, ch, fps), (dw, dh, _) = profile.color, profile.depth

    def rows(m: np.ndarray) -> tuple[tuple[float, ...], ...]:
        return tuple(tuple(float(v) for v in r) for r in m)

    return SimulatedLayout(video_intrinsics(cw, ch, COLOR_FOV_DEG), video_intrinsics(dw, dh, DEPTH_FOV_DEG), fps,
                           gyro_hz if profile.imu else 0, accel_hz if profile.imu else 0,
                           profile.options.depth_units_m or 0.001, rows(to_from(DEPTH_TO_COLOR)),
                           rows(np.linalg.inv(to_from(DEPTH_TO_IMU))))


def default_imu_rates(profile: CaptureProfile, imu_chip: str) -> tuple[int, int]:
    """The gyro and accelerometer rates a profile opens the chip at (0: the device's default)."""
    rates = D455_IMU[imu_chip]
    return profile.gyro_fps or rates["gyro"][0], profile.accel_fps or rates["accel"][0]


class FrameProvider(Protocol):
    """What the software D455 films, per frame index and IMU sample index (see SimulatedLayout)."""

    frames: int  # frame pairs it has (0: endless); the stream ends after them

    def color(self, i: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB."""
        ...

    def depth(self, i: int) -> np.ndarray:
        """(H, W) uint16 in the layout's depth units, 0 = no reading, from the depth imager's pose."""
        ...

    def motion(self, stream: str, k: int) -> tuple[float, float, float]:
        """The k-th gyro (rad/s) or accelerometer (m/s²) sample, as float32 would hold it."""
        ...

    def groundtruth_tum(self) -> str:
        """The colour camera's true poses at the frames' stamps (TUM text), "" if unknown."""
        ...


ProviderFactory = Callable[[SimulatedLayout], FrameProvider]


class SyntheticPattern:
    """Deterministic image content for the software D455: a textured, moving colour pattern and a
    bumpy depth surface.

    Frames are windows into larger precomputed images (cheap to cut, so the source costs little
    next to the recorder), shifted a little each frame, back and forth as a hand sweeps a camera
    (a window that wrapped round would jump, which no camera does); fixed-seed noise makes the compression
    figures closer to a real sensor's than flat test patterns would.
    """

    PAD = 96
    frames = 0  # endless

    @classmethod
    def for_layout(cls, layout: SimulatedLayout) -> SyntheticPattern:
        return cls((layout.color.width, layout.color.height), (layout.depth.width, layout.depth.height))

    def groundtruth_tum(self) -> str:
        return ""  # no rigid motion explains these frames

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
        dx, dy = self._sweep(3 * i), self._sweep(2 * i)
        return np.ascontiguousarray(img[dy:dy + wh[1], dx:dx + wh[0]])

    @classmethod
    def _sweep(cls, t: int) -> int:
        """0, 1, ... PAD, PAD - 1, ... 0, 1, ...: a triangle wave."""
        t %= 2 * cls.PAD
        return t if t <= cls.PAD else 2 * cls.PAD - t

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
    """One sample the software device pushed (or, paced and late, skipped): for tests to compare."""

    stream: str
    frame_number: int
    stamp_ns: int


class SoftwareDeviceBackend:
    """pyrealsense2's software device posing as a D455: every D455 colour/depth profile and the
    IMU rates of the chosen chip, D455-like calibration and options. Frames of a `FrameProvider`
    (`frames_from` makes one for the opened streams; default the synthetic pattern) are pushed into
    the sensors and come back through `rs.syncer` as real rs frames; a provider with a ground truth
    puts it into the device's description (the recording's `groundtruth` record).

    On demand (default) a frame pair and the IMU samples up to the next frame time are pushed
    each time the recorder asks, so sensor time runs as fast as the recorder takes frames;
    `paced` pushes on the sensor clock in wall time, like a camera, from the recorder's first `wait`
    (a recorder still setting up its outputs loses no frames to it). `frames` ends the stream
    after that many pairs (or the provider's last); `unplug_after` raises DeviceLost after that many,
    like a pulled cable. `pushed` logs what went in, for tests.
    """

    START_NS = START_NS
    MAX_LAG_S = 0.25

    def __init__(self, *, frames: int = 0, paced: bool = False, unplug_after: int = 0, imu_chip: str = "bmi085",
                 seed: int = 0, serial: str = "SW-D455-0001", frames_from: ProviderFactory | None = None) -> None:
        self.frames = frames
        self.frames_from = frames_from
        self.paced = paced
        self.realtime = paced
        self.unplug_after = unplug_after
        self.imu_chip = imu_chip
        self.seed = seed
        self.serial = serial
        self.pushed: list[Pushed] = []
        self.skipped: list[Pushed] = []  # paced: samples lost because the recorder was late
        self.pattern: FrameProvider | None = None
        self._i = 0
        self._k = {"gyro": 0, "accel": 0}
        self._t0 = 0.0
        self._started: list[Any] = []
        self._done = False

    # building the device

    def _build(self) -> None:
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
        self._add_video_streams(uid)
        self._add_motion_streams(uid)
        self._register_extrinsics()
        self._add_options()
        self._dev = dev

    def _add_video_streams(self, uid: Iterator[int]) -> None:
        """Every depth and colour profile of a D455, each with pinhole intrinsics from its field of view."""
        for table, sensor, stream, fmt, bpp, fov, store, default in (
                (D455_DEPTH, self._depth_s, rs.stream.depth, rs.format.z16, 2, DEPTH_FOV_DEG, self._dprof,
                 (848, 480, 30)),
                (D455_COLOR, self._color_s, rs.stream.color, rs.format.rgb8, 3, COLOR_FOV_DEG, self._cprof,
                 (1280, 720, 30))):
            for (w, h), rates in table.items():
                for fps in rates:
                    vs = rs.video_stream()
                    vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps = stream, 0, next(uid), w, h, fps
                    vs.bpp, vs.fmt = bpp, fmt
                    intr = rs.intrinsics()
                    k = video_intrinsics(w, h, fov)
                    intr.width, intr.height, intr.fx, intr.fy = w, h, k.fx, k.fy
                    intr.ppx, intr.ppy = k.cx, k.cy
                    intr.model = rs.distortion.brown_conrady
                    intr.coeffs = [0.0] * 5
                    vs.intrinsics = intr
                    store[(w, h, fps)] = sensor.add_video_stream(vs, (w, h, fps) == default)

    def _add_motion_streams(self, uid: Iterator[int]) -> None:
        """The gyro and accelerometer rates of the IMU chip, with D455-like intrinsics and noise."""
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

    def _register_extrinsics(self) -> None:
        to_color, to_imu = rs.extrinsics(), rs.extrinsics()
        to_color.rotation, to_color.translation = (list(v) for v in DEPTH_TO_COLOR)
        to_imu.rotation, to_imu.translation = (list(v) for v in DEPTH_TO_IMU)
        for dp in self._dprof.values():
            for cp in self._cprof.values():
                dp.register_extrinsics_to(cp, to_color)
            for mp in self._mprof.values():
                dp.register_extrinsics_to(mp, to_imu)

    def _add_options(self) -> None:
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

    # Backend

    def open(self, profile: CaptureProfile) -> DeviceDescription:
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
        rates = [res.profiles[s][1].fps() if s in res.profiles else 0 for s in MOTION_STREAMS]
        layout = simulated_layout(profile, *rates)
        if self.frames_from is None:
            self.pattern = SyntheticPattern(profile.color[:2], profile.depth[:2], seed=self.seed)
        else:
            self.pattern = self.frames_from(layout)
        if self.pattern.frames and not 0 < self.frames <= self.pattern.frames:
            self.frames = self.pattern.frames  # the provider's last frame ends the stream
        desc = describe(self._dev, res, "software", options)
        desc.groundtruth_tum = self.pattern.groundtruth_tum()
        return desc

    def stamp_of(self, stream: str, n: int) -> int:
        """Sensor time of the n-th pushed sample of a stream (integer ns on the device clock)."""
        return stamp_ns(self._res.profiles[stream][1].fps() if stream in MOTION_STREAMS else self._fps, n)

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
            self._t0 = self._t0 or time.monotonic()  # the sensor clock starts with the first take
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
        assert self.pattern is not None
        t_video = self.stamp_of("color", self._i)
        if self._profile.imu:
            stream = min(MOTION_STREAMS, key=lambda st: (self.stamp_of(st, self._k[st]), st))
            ts = self.stamp_of(stream, self._k[stream])
            if ts < t_video:
                k = self._k[stream]
                x, y, z = self.pattern.motion(stream, k)
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
        for sensor, key, arr, bpp in ((self._color_s, "color", self.pattern.color(i), 3),
                                      (self._depth_s, "depth", self.pattern.depth(i), 2)):
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
