"""What a recording is made of and what it reports: the camera's TF frames, a message as written,
per-stream counts, the recorder's status line and result, the writer's settings and output names."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from octolog.kit.errors import RecorderError
from octolog.kit.geometry import invert
from octolog.kit.tftree import LINK_FROM_OPTICAL
from octolog.recorder.capture import Capture, DeviceDescription
from octolog.schemas.topics import Topic

STREAMS = ("color", "aligned_depth", "depth", "gyro", "accel")
JPEG_FORMAT = "rgb8; jpeg compressed bgr8"  # image_transport's spelling
PNG_FORMAT = "16UC1; png compressed"  # lossless 16-bit PNG of the depth image, in sensor units



def frame_names(prefix: str) -> dict[str, str]:
    """The camera's TF frames, realsense-ros style (`camera_link`, `camera_color_optical_frame`, ...)."""
    return {"color": f"{prefix}_color_optical_frame", "depth": f"{prefix}_depth_optical_frame",
            "gyro": f"{prefix}_gyro_optical_frame", "accel": f"{prefix}_accel_optical_frame", "link": f"{prefix}_link"}


def camera_transforms(device: DeviceDescription, frames: dict[str, str]) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, parent_from_child) of the camera's static tree: link -> depth -> colour, IMU."""
    f = frames
    out = [(f["link"], f["depth"], LINK_FROM_OPTICAL), (f["depth"], f["color"], invert(device.color_from_depth))]
    for s in ("gyro", "accel"):
        m = getattr(device, f"depth_from_{s}")
        if m is not None and getattr(device, f"{s}_fps"):
            out.append((f["depth"], f[s], m))
    return out


@dataclass(frozen=True)
class Encoded:
    """One message as written: its topic, CDR bytes and sensor time."""

    topic: Topic
    data: bytes
    stamp_ns: int


Sink = Callable[[Capture, list[Encoded]], None]


@dataclass
class StreamStats:
    frames: int = 0  # written
    device_gaps: int = 0  # frame numbers the device skipped
    queue_drops: int = 0  # the writer was behind and its queue full
    unpaired: int = 0  # aligned depth without a colour partner
    unwritten: int = 0  # left in the queue after a write failure
    live_drops: int = 0  # a live sink (bus, Rerun) had no room
    last_frame_number: int = -1

    @property
    def dropped(self) -> int:
        """Frames lost to the file, whatever the cause."""
        return self.device_gaps + self.queue_drops + self.unpaired + self.unwritten


@dataclass(frozen=True)
class RecorderStatus:
    elapsed_s: float
    frames: dict[str, int]
    rates_hz: dict[str, float]
    dropped: dict[str, int]
    live_drops: int
    messages: int
    flushed_messages: int  # messages in chunks already on disk
    mb_written: float
    mb_per_s: float
    free_mb: float
    queue: int
    files: int
    held_back: int = 0  # frames not published: the live tracker had RecorderConfig.publish_window in hand


@dataclass
class RecordResult:
    paths: list[Path] = field(default_factory=list)
    messages: int = 0
    bytes: int = 0
    streams: dict[str, StreamStats] = field(default_factory=dict)
    stop_reason: str = ""
    wall_s: float = 0.0
    first_stamp_ns: int = 0
    last_stamp_ns: int = 0
    held_back: int = 0  # RGB-D frames recorded but not published (RecorderConfig.publish_window)

    @property
    def dropped(self) -> int:
        return sum(s.dropped for s in self.streams.values())


@dataclass(frozen=True)
class Encoding:
    color_codec: str = "jpeg"  # raw | jpeg
    jpeg_quality: int = 95
    depth_codec: str = "raw"  # raw | png
    png_level: int = 1


@dataclass(frozen=True)
class WriterParams:
    """The writer's settings, built once from a validated RecorderConfig (`RecorderConfig.writer_params`)."""

    compression: str  # MCAP chunk compression: none | lz4 | zstd
    chunk_size_bytes: int
    encoding: Encoding
    split_size_bytes: int  # 0: no size split
    split_duration_ns: int  # 0: no time split
    queue_size: int  # captures waiting for the writer
    block_when_full: bool  # wait instead of dropping (a source that can wait)
    encode_threads: int
    min_free_bytes: int  # stop cleanly when the disk has less free
    frame_prefix: str  # topic prefix of the frames (camera/...)


def output_paths(out: Path, *, split: bool, overwrite: bool) -> Callable[[int], Path]:
    """The file name for part i; refuses to overwrite an existing recording unless asked."""
    out = Path(out)
    if out.is_dir():
        raise RecorderError(f"{out} is a directory; give a file name like {out / 'recording.mcap'}")
    stem = out.name.removesuffix(".mcap")

    def part(i: int) -> Path:
        return out.with_name(f"{stem}_{i:04d}.mcap") if split else out

    existing = sorted(out.parent.glob(f"{stem}_[0-9][0-9][0-9][0-9].mcap")) if split else \
        ([out] if out.exists() else [])
    if existing:
        if not overwrite:
            raise RecorderError(f"{existing[0]} exists; pass --overwrite to replace it")
        for p in existing:
            p.unlink()
    return part


def format_status(s: RecorderStatus) -> str:
    """One line: frames and rate per stream, drops, write rate, free disk."""
    parts = [f"{s.elapsed_s:6.1f} s"]
    for name in STREAMS:
        if s.frames.get(name) or s.dropped.get(name):
            drop = f" -{s.dropped[name]}" if s.dropped.get(name) else ""
            parts.append(f"{name} {s.frames[name]} ({s.rates_hz[name]:.0f} Hz){drop}")
    drops = sum(s.dropped.values())
    parts.append(f"dropped {drops}" + (f" +{s.live_drops} live" if s.live_drops else ""))
    if s.held_back:
        parts.append(f"held back {s.held_back} (tracker busy)")
    parts.append(f"{s.mb_per_s:5.1f} MB/s, {s.mb_written:.0f} MB")
    parts.append(f"{s.free_mb / 1e3:.1f} GB free")
    if s.files > 1:
        parts.append(f"file {s.files}")
    parts.append(f"msgs {s.messages} ({s.flushed_messages} on disk)")
    return " | ".join(parts)
