"""Recorder settings: which streams at which profiles, how they are encoded, how files are cut."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from octolog.kit.config import to_json
from octolog.kit.errors import ConfigError
from octolog.kit.mcaplog import COMPRESSIONS
from octolog.recorder.capture import Backend, CaptureProfile, DeviceDescription, DeviceOptions
from octolog.recorder.livesink import LiveSink
from octolog.recorder.realsense_camera import RealSenseBackend
from octolog.recorder.writer import Recorder
from octolog.recorder.recording_types import Encoding, WriterParams
from octolog.recorder.software_d455 import D455_IMU, ProviderFactory, SoftwareDeviceBackend

BACKENDS = ("realsense", "software")
COLOR_CODECS = ("raw", "jpeg")
DEPTH_CODECS = ("raw", "png")
EMITTER = ("", "off", "on", "auto")
IMU_CHIPS = tuple(D455_IMU)  # the chips the software D455 can pose with
SCENES = ("room", "pattern")  # what the software D455 films (SoftwareConfig.scene)
MOTIONS = ("walk", "turns")
PRESETS = ("", "custom", "default", "hand", "high_accuracy", "high_density", "medium_density")


@dataclass(frozen=True)
class ColorConfig:
    width: int = 1280
    height: int = 720
    fps: int = 30


@dataclass(frozen=True)
class DepthConfig:
    width: int = 848
    height: int = 480
    fps: int = 30


@dataclass(frozen=True)
class SoftwareConfig:
    """The software device (no camera needed): synthetic frames pushed through pyrealsense2."""

    frames: int = 0  # frame pairs to push, then the stream ends (0: until stopped; room: --duration's, else one walk)
    paced: bool = False  # push at the sensor rate in wall time (a live camera) instead of on demand
    unplug_after: int = 0  # simulate the camera vanishing after this many frame pairs (0: never)
    imu_chip: str = "bmi085"  # bmi085: gyro 200/400 Hz, accel 100/200 Hz; bmi055: accel 63/250 Hz
    # what it films: "room" (the synthetic room along a known path, rendered ahead by the shell:
    # shell/simcamera.py) or "pattern" (flat pictures and sine waves: the recorder alone, cheap)
    scene: str = "room"
    motion: str = "walk"  # room: walk (a hand-held walk round the room) or turns (the walk with fast head turns)
    seed: int = 0  # room: another draw of the textures and of the depth and IMU noise
    depth_bias_px: float = 0.0  # room: the depth's disparity offset (reads short if > 0), -1 to 1 px
    imu_time_offset_ms: float = 0.0  # room: the IMU's stamps this much behind the camera's (-100 to 100)
    imu_rotation_deg: float = 0.0  # room: the IMU turned this much about the camera's x axis from its calibration


@dataclass(frozen=True)
class RecorderConfig:
    backend: str = "realsense"  # realsense (a camera) or software (pyrealsense2's software device)
    serial: str = ""  # pick this camera when several are attached
    color: ColorConfig = field(default_factory=ColorConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    aligned_depth: bool = True  # depth registered to colour (what the tracker consumes)
    raw_depth: bool = False  # depth in its own sensor frame, as measured
    imu: bool = True
    gyro_fps: int = 0  # 0: the device's default rate (D455: 200 Hz)
    accel_fps: int = 0  # 0: the device's default rate (D455: 63 or 100 Hz, by IMU chip)
    # device options; empty / negative / 0 leaves the device's own setting
    depth_units_m: float = 0.0  # metres per depth unit (D455 default 0.001)
    visual_preset: str = ""
    emitter: str = ""
    color_auto_exposure: str = ""  # "", "on", "off"
    depth_auto_exposure: str = ""
    color_exposure: float = 0.0  # device units, passed as is (D455 colour: 100 µs steps)
    depth_exposure: float = 0.0  # device units (D455 depth: µs)
    # encoding and files: defaults measured with bench/recorder.py (JPEG colour + raw depth + lz4
    # sustains the D455 default profile at the least CPU; PNG depth saves ~30% disk for ~40% more CPU)
    color_codec: str = "jpeg"
    jpeg_quality: int = 95
    depth_codec: str = "raw"
    png_level: int = 1
    compression: str = "lz4"
    chunk_size_mb: float = 2.0  # a killed recorder loses at most one unfinished chunk
    split_size_mb: float = 0.0  # start a new file after this many MB (0: one file)
    split_duration_s: float = 0.0  # start a new file after this much sensor time (0: one file)
    queue_frames: int = 30  # capture -> writer queue (frame sets); beyond it frames are dropped, counted
    encode_threads: int = 2
    live_queue_frames: int = 4  # per live sink (bus, Rerun); a slow consumer loses frames there, counted
    # --publish: at most this many frames out on camera/rgbd that no tracker/status has answered yet;
    # a frame beyond them is recorded but not published (nor encoded for the wire): a tracker that
    # far behind would skip it. 0: publish every frame (no tracker needed). `octolog run` live: 2
    publish_window: int = 0
    # with publish_window: hold a frame back only if the oldest unanswered one is also more than this
    # much sensor time older (a live tracker tracks a burst in order, tracker.live_lag_ms); 0: by
    # count alone. `octolog run` live: the tracker's live_lag_ms
    publish_lag_ms: float = 0.0
    # --publish with JPEG colour: the frames' depth on camera/rgbd/compressed, lossless either way:
    # "zstd" (octolog's own, docs/formats.md: less than half PNG's CPU here and in the tracker; the
    # session log's depth topic is then readable by octolog only) or "png" (any PNG reader, ROS tools)
    wire_depth: str = "zstd"
    min_free_mb: float = 256.0  # stop cleanly before the disk is full
    frame_prefix: str = "camera"
    # --publish: stages that must be up before capture starts (e.g. "tracker"), so none misses frames
    wait_for: tuple[str, ...] = ()
    wait_timeout_s: float = 60.0  # tf frame names: camera_link, camera_color_optical_frame, ...
    software: SoftwareConfig = field(default_factory=SoftwareConfig)

    def validate(self) -> None:
        def one_of(key: str, value: str, allowed: tuple[str, ...]) -> None:
            if value not in allowed:
                raise ConfigError(f"recorder.{key} {value!r}: want one of {', '.join(repr(a) for a in allowed)}")

        one_of("backend", self.backend, BACKENDS)
        one_of("color_codec", self.color_codec, COLOR_CODECS)
        one_of("depth_codec", self.depth_codec, DEPTH_CODECS)
        one_of("compression", self.compression, COMPRESSIONS)
        one_of("wire_depth", self.wire_depth, ("zstd", "png"))
        one_of("emitter", self.emitter, EMITTER)
        one_of("visual_preset", self.visual_preset, PRESETS)
        one_of("color_auto_exposure", self.color_auto_exposure, ("", "on", "off"))
        one_of("depth_auto_exposure", self.depth_auto_exposure, ("", "on", "off"))
        one_of("software.imu_chip", self.software.imu_chip, IMU_CHIPS)
        one_of("software.scene", self.software.scene, SCENES)
        one_of("software.motion", self.software.motion, MOTIONS)
        if not abs(self.software.depth_bias_px) <= 1.0:
            raise ConfigError(f"recorder.software.depth_bias_px {self.software.depth_bias_px}: want -1 to 1 px")
        if not abs(self.software.imu_time_offset_ms) <= 100.0 or not abs(self.software.imu_rotation_deg) <= 45.0:
            raise ConfigError("recorder.software.imu_time_offset_ms, imu_rotation_deg: want -100 to 100 ms, "
                              "-45 to 45 degrees")
        for key, v in (("color", self.color), ("depth", self.depth)):
            if v.width <= 0 or v.height <= 0 or v.fps <= 0:
                raise ConfigError(f"recorder.{key} {v.width}x{v.height}@{v.fps}: want positive size and rate")
        if not (self.aligned_depth or self.raw_depth):
            raise ConfigError("recorder: aligned_depth and raw_depth are both off; record at least one depth")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"recorder.jpeg_quality {self.jpeg_quality}: want 1..100")
        if not 0 <= self.png_level <= 9:
            raise ConfigError(f"recorder.png_level {self.png_level}: want 0..9")
        for key in ("chunk_size_mb",):
            if getattr(self, key) <= 0:
                raise ConfigError(f"recorder.{key} {getattr(self, key)}: want > 0")
        for key in ("split_size_mb", "split_duration_s", "min_free_mb", "publish_window", "publish_lag_ms",
                    "depth_units_m", "color_exposure", "depth_exposure", "gyro_fps", "accel_fps"):
            if getattr(self, key) < 0:
                raise ConfigError(f"recorder.{key} {getattr(self, key)}: want >= 0")
        for key in ("queue_frames", "encode_threads", "live_queue_frames"):
            if getattr(self, key) < 1:
                raise ConfigError(f"recorder.{key} {getattr(self, key)}: want >= 1")
        if self.software.frames < 0 or self.software.unplug_after < 0:
            raise ConfigError("recorder.software.frames and unplug_after: want >= 0")

    def writer_params(self, *, block_when_full: bool = False) -> WriterParams:
        """The writer's settings from this config, after the one check of every value."""
        self.validate()
        return WriterParams(
            compression=self.compression, chunk_size_bytes=int(self.chunk_size_mb * 2**20),
            encoding=Encoding(self.color_codec, self.jpeg_quality, self.depth_codec, self.png_level),
            split_size_bytes=int(self.split_size_mb * 1e6), split_duration_ns=int(self.split_duration_s * 1e9),
            queue_size=self.queue_frames, block_when_full=block_when_full, encode_threads=self.encode_threads,
            min_free_bytes=int(self.min_free_mb * 1e6), frame_prefix=self.frame_prefix)


# --- factories: config -> plain constructor arguments -------------------------------------------


def capture_profile(cfg: RecorderConfig) -> CaptureProfile:
    """The streams and device options to ask the backend for."""

    def onoff(v: str) -> bool | None:
        return None if v == "" else v == "on"

    opts = DeviceOptions(
        depth_units_m=cfg.depth_units_m or None, visual_preset=cfg.visual_preset or None,
        emitter=cfg.emitter or None, color_auto_exposure=onoff(cfg.color_auto_exposure),
        depth_auto_exposure=onoff(cfg.depth_auto_exposure), color_exposure=cfg.color_exposure or None,
        depth_exposure=cfg.depth_exposure or None)
    return CaptureProfile(color=(cfg.color.width, cfg.color.height, cfg.color.fps),
                          depth=(cfg.depth.width, cfg.depth.height, cfg.depth.fps), imu=cfg.imu,
                          gyro_fps=cfg.gyro_fps, accel_fps=cfg.accel_fps, align=cfg.aligned_depth,
                          raw_depth=cfg.raw_depth, options=opts)


def make_backend(cfg: RecorderConfig, frames_from: ProviderFactory | None = None) -> Backend:
    """The configured frame source: a RealSense camera, or the software D455 filming what
    `frames_from` makes (the shell's rendered room, shell/simcamera.py; None: the flat pattern)."""
    if cfg.backend == "software":
        s = cfg.software
        return SoftwareDeviceBackend(frames=s.frames, paced=s.paced, unplug_after=s.unplug_after,
                                     imu_chip=s.imu_chip, frames_from=frames_from)
    return RealSenseBackend(cfg.serial)


def make_recorder(cfg: RecorderConfig, part: Callable[[int], Path], device: DeviceDescription, *,
                  sinks: Sequence[LiveSink] = (), block_when_full: bool = False) -> Recorder:
    """The writer side (recorder.writer.Recorder) for a resolved device."""
    return Recorder(part, device, cfg.writer_params(block_when_full=block_when_full), config_json=to_json(cfg),
                    sinks=sinks)
