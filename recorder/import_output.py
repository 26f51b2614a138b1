"""What every import writes: the recorder's MCAP layout, the result record, and the output file.

The layout is the recorder's (schemas.topics CAMERA_TOPICS): colour rgb8 on camera/color/image_raw,
16UC1 depth on camera/aligned_depth_to_color/image_raw when registered to colour or
camera/depth/image_rect_raw when raw, a camera_info beside every image, IMU on camera/accel/sample and
camera/gyro/sample, extrinsics on /tf_static. Metadata records: "calibration" (depth_scale_m, ...),
"source" (what was imported) and, for TUM, "groundtruth" (key "tum": the groundtruth.txt text).
Stamps are the sensor's, in integer nanoseconds; every message's log time is its stamp.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics
from octolog.kit.mcaplog import McapWriter
from octolog.schemas import codec

SUPPORTED = ("a TUM RGB-D folder (rgb.txt, depth.txt), a ROS 1 .bag (RealSense or other) "
             "or a ROS 2 bag (.db3 or .mcap file, or a rosbag2 folder with metadata.yaml)")
DEFAULT_DEPTH_SCALE_M = 0.001  # ROS convention for 16UC1 depth: millimetres

COLOR_FRAME = "camera_color_optical_frame"
DEPTH_FRAME = "camera_depth_optical_frame"
ACCEL_FRAME = "camera_accel_optical_frame"
GYRO_FRAME = "camera_gyro_optical_frame"


@dataclass
class ImportResult:
    """What an import wrote: messages per output topic (no leading slash) and what it found."""

    source: Path
    output: Path
    kind: str  # tum | realsense-bag | realsense-db3 | rosbag1 | rosbag2
    counts: dict[str, int] = field(default_factory=dict)
    depth_scale_m: float | None = None
    depth_registered: bool | None = None  # True: aligned to colour; False: raw depth; None: no depth
    skipped: dict[str, int] = field(default_factory=dict)  # source topics not imported -> messages
    notes: list[str] = field(default_factory=list)

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def detect_kind(source: Path) -> str:
    """'tum', 'rosbag1' or 'rosbag2'; an InputError saying what is supported otherwise."""
    if not source.exists():
        raise InputError(f"{source}: no such file or folder")
    if source.is_dir():
        if (source / "rgb.txt").is_file() or (source / "depth.txt").is_file():
            return "tum"
        if (source / "metadata.yaml").is_file():
            return "rosbag2"
        raise InputError(f"{source}: unsupported source folder (want {SUPPORTED})")
    if source.suffix == ".bag":
        return "rosbag1"
    if source.suffix in (".db3", ".mcap"):
        return "rosbag2"
    raise InputError(f"{source}: unsupported source {source.suffix or 'file'} (want {SUPPORTED})")


class ImportSink:
    """Encodes and writes messages, counting per topic."""

    def __init__(self, writer: Any, progress: Callable[[int], None] | None) -> None:
        self.writer = writer
        self.counts: dict[str, int] = {}
        self.progress = progress

    def put(self, topic: str, msgtype: str, msg: Any, stamp: int) -> None:
        self.writer.write(topic, msgtype, codec.encode(msg, msgtype), log_time_ns=stamp, publish_time_ns=stamp)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        if self.progress is not None:
            self.progress(self.writer.count)

    def metadata(self, name: str, data: dict[str, Any]) -> None:
        self.writer.add_metadata(name, {k: str(v) for k, v in data.items()})


@contextmanager
def open_output(output: Path, *, overwrite: bool, compression: str,
            progress: Callable[[int], None] | None) -> Iterator[ImportSink]:
    """An MCAP written beside OUTPUT and moved into place only when complete."""

    output = Path(output)
    if output.exists() and not overwrite:
        raise InputError(f"{output}: exists; pass overwrite (--overwrite) to replace it")
    if output.is_dir():
        raise InputError(f"{output}: is a folder; want an .mcap file name")
    partial = output.with_name(output.name + ".partial")
    try:
        with McapWriter(partial, compression=compression) as writer:
            yield ImportSink(writer, progress)
        os.replace(partial, output)
    finally:
        partial.unlink(missing_ok=True)


def intrinsics_fields(prefix: str, intr: Intrinsics, model: str = "") -> dict[str, str]:
    return {
        f"{prefix}_width": str(intr.width), f"{prefix}_height": str(intr.height),
        f"{prefix}_fx": repr(intr.fx), f"{prefix}_fy": repr(intr.fy),
        f"{prefix}_cx": repr(intr.cx), f"{prefix}_cy": repr(intr.cy),
        f"{prefix}_distortion_model": model or ("plumb_bob" if intr.distortion else "none"),
        f"{prefix}_distortion": " ".join(repr(float(x)) for x in intr.distortion),
    }
