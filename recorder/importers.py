"""Importers: TUM RGB-D folders, RealSense and other ROS 1/ROS 2 bags into the recorder's MCAP layout.

The layout is the recorder's (schemas.topics CAMERA_TOPICS): colour rgb8 on camera/color/image_raw,
16UC1 depth on camera/aligned_depth_to_color/image_raw when registered to colour or
camera/depth/image_rect_raw when raw, a camera_info beside every image, IMU on camera/accel/sample and
camera/gyro/sample, extrinsics on /tf_static. Metadata records: "calibration" (depth_scale_m, ...),
"source" (what was imported) and, for TUM, "groundtruth" (key "tum": the groundtruth.txt text).
Stamps are the sensor's, in integer nanoseconds; every message's log time is its stamp.
"""

from __future__ import annotations

import json
import os
import re
import sqlite3
import struct
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.errors import InputError, OctologError
from octolog.kit.geometry import Intrinsics, invert, pose_to_matrix
from octolog.schemas import codec
from octolog.schemas.topics import (
    ACCEL,
    ALIGNED_DEPTH,
    ALIGNED_DEPTH_INFO,
    CAMERA_TOPICS,
    COLOR,
    COLOR_INFO,
    DEPTH,
    DEPTH_INFO,
    GYRO,
    TF_STATIC,
    Topic,
)

SUPPORTED = ("a TUM RGB-D folder (rgb.txt, depth.txt), a ROS 1 .bag (RealSense or other) "
             "or a ROS 2 bag (.db3 or .mcap file, or a rosbag2 folder with metadata.yaml)")
DEFAULT_DEPTH_SCALE_M = 0.001  # ROS convention for 16UC1 depth: millimetres

COLOR_FRAME = "camera_color_optical_frame"
DEPTH_FRAME = "camera_depth_optical_frame"
ACCEL_FRAME = "camera_accel_optical_frame"
GYRO_FRAME = "camera_gyro_optical_frame"

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMU = "sensor_msgs/msg/Imu"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
BAG_TYPES = (IMAGE, COMPRESSED, CAMERA_INFO, IMU, TF_MESSAGE)

_BY_NAME = {t.name: t for t in CAMERA_TOPICS}
# Image topics whose pixels the layout fixes, and the camera_info topic that goes with each.
_COLOR_TOPICS = {COLOR.name}
_DEPTH_TOPICS = {ALIGNED_DEPTH.name, DEPTH.name}
_INFO_FOR = {COLOR.name: COLOR_INFO, ALIGNED_DEPTH.name: ALIGNED_DEPTH_INFO, DEPTH.name: DEPTH_INFO}


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


# --- entry points -------------------------------------------------------------------------------


def import_source(source: str | Path, output: Path, *, overwrite: bool = False,
                  topic_map: dict[str, str] | None = None, compression: str = "zstd",
                  depth_scale_m: float | None = None,
                  progress: Callable[[int], None] | None = None) -> ImportResult:
    """Import a TUM folder or a ROS 1/ROS 2 bag (RealSense or other) into an MCAP in the recorder's layout."""
    source = Path(source)
    kind = detect_kind(source)
    if kind == "tum":
        if topic_map:
            raise InputError(f"{source}: --map applies to bags, not to a TUM folder")
        return import_tum(source, output, overwrite=overwrite, compression=compression, progress=progress)
    return import_bag(source, output, overwrite=overwrite, topic_map=topic_map, compression=compression,
                      depth_scale_m=depth_scale_m, progress=progress)


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


def parse_topic_map(items: Iterable[str]) -> dict[str, str]:
    """`SRC=DST` strings (the CLI's repeated --map) as a dict; source names keep their leading slash."""
    out: dict[str, str] = {}
    for item in items:
        src, sep, dst = item.partition("=")
        if not sep or not src.strip() or not dst.strip():
            raise InputError(f"--map {item!r}: want SOURCE_TOPIC=TARGET_TOPIC")
        src = "/" + src.strip().lstrip("/")
        if src in out:
            raise InputError(f"--map {item!r}: {src} mapped twice")
        out[src] = dst.strip().strip("/")
    return out


# --- output -------------------------------------------------------------------------------------


class _Sink:
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
def _output(output: Path, *, overwrite: bool, compression: str,
            progress: Callable[[int], None] | None) -> Iterator[_Sink]:
    """An MCAP written beside OUTPUT and moved into place only when complete."""
    from octolog.kit.mcaplog import McapWriter

    output = Path(output)
    if output.exists() and not overwrite:
        raise InputError(f"{output}: exists; pass overwrite (--overwrite) to replace it")
    if output.is_dir():
        raise InputError(f"{output}: is a folder; want an .mcap file name")
    partial = output.with_name(output.name + ".partial")
    try:
        with McapWriter(partial, compression=compression) as writer:
            yield _Sink(writer, progress)
        os.replace(partial, output)
    finally:
        partial.unlink(missing_ok=True)


# --- TUM ----------------------------------------------------------------------------------------


def import_tum(folder: Path, output: Path, *, overwrite: bool = False, compression: str = "zstd",
               intrinsics: Intrinsics | None = None,
               progress: Callable[[int], None] | None = None) -> ImportResult:
    """TUM RGB-D folder -> MCAP: every listed colour and depth image (registered depth, 1/5000 m),
    accelerometer.txt as Imu, groundtruth.txt as metadata; stamps exact from the decimal seconds."""
    import cv2

    from octolog.replay.tum import TUM_DEPTH_SCALE_M, _read_list, _read_png, open_tum, readout_for, seconds_to_ns

    folder = Path(folder)
    seq = open_tum(folder, intrinsics)  # validates the folder; intrinsics from the sequence name unless given
    intr = seq.intrinsics
    rgb = sorted(_read_list(folder / "rgb.txt"), key=lambda r: r[0])
    depth = sorted(_read_list(folder / "depth.txt"), key=lambda r: r[0])
    accel = _read_accelerometer(folder / "accelerometer.txt", seconds_to_ns)
    # Colour before depth before IMU at equal stamps; stable, so list order is kept.
    events = sorted([(t, 0, i) for i, (t, _) in enumerate(rgb)] + [(t, 1, i) for i, (t, _) in enumerate(depth)]
                    + [(t, 2, i) for i, (t, _) in enumerate(accel)], key=lambda e: (e[0], e[1]))
    result = ImportResult(folder, Path(output), "tum", depth_scale_m=TUM_DEPTH_SCALE_M, depth_registered=True)
    with _output(output, overwrite=overwrite, compression=compression, progress=progress) as sink:
        for stamp, what, i in events:
            if what == 0:
                img = _read_png(folder / rgb[i][1], cv2.IMREAD_COLOR)
                if img.ndim != 3 or img.shape[2] != 3:
                    raise InputError(f"{folder / rgb[i][1]}: not a 3-channel colour image")
                _check_size(folder / rgb[i][1], img, intr)
                sink.put(COLOR.name, COLOR.msgtype, codec.image_msg(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), stamp,
                                                                    COLOR_FRAME), stamp)
                sink.put(COLOR_INFO.name, COLOR_INFO.msgtype, codec.camera_info_msg(intr, stamp, COLOR_FRAME), stamp)
            elif what == 1:
                img = _read_png(folder / depth[i][1], cv2.IMREAD_ANYDEPTH)
                if img.dtype != np.uint16 or img.ndim != 2:
                    raise InputError(f"{folder / depth[i][1]}: depth must be a 16-bit single-channel PNG")
                _check_size(folder / depth[i][1], img, intr)
                # Registered depth: realsense-ros stamps it in the colour optical frame.
                sink.put(ALIGNED_DEPTH.name, ALIGNED_DEPTH.msgtype, codec.image_msg(img, stamp, COLOR_FRAME), stamp)
                sink.put(ALIGNED_DEPTH_INFO.name, ALIGNED_DEPTH_INFO.msgtype,
                         codec.camera_info_msg(intr, stamp, COLOR_FRAME), stamp)
            else:
                sink.put(ACCEL.name, ACCEL.msgtype, codec.imu_msg(stamp, ACCEL_FRAME, linear_acceleration=accel[i][1]),
                         stamp)
        sink.metadata("calibration", {
            "depth_scale_m": repr(TUM_DEPTH_SCALE_M),
            "depth_scale_source": "TUM RGB-D: 5000 depth units per metre",
            "depth_registered_to_color": "true",
            # the colour camera's rolling-shutter readout time (s), for the tracker; 0 = not known
            "color_readout_s": repr(readout_for(folder)),
            **_intrinsics_fields("color", intr),
            "intrinsics_source": ("given on import" if intrinsics is not None
                                  else f"TUM RGB-D ROS default calibration for {folder.resolve().name}"),
        })
        sink.metadata("source", {"kind": "tum", "path": str(folder.resolve()), "importer": "octolog import",
                                 "rgb_images": len(rgb), "depth_images": len(depth),
                                 "accelerometer_samples": len(accel), "pairs_within_20ms": len(seq)})
        if seq.groundtruth is not None:
            sink.metadata("groundtruth", {"tum": seq.groundtruth.read_text()})
        result.counts = dict(sink.counts)
    if not accel:
        result.notes.append("no accelerometer.txt: no IMU written")
    if seq.groundtruth is None:
        result.notes.append("no groundtruth.txt: no ground truth written")
    return result


def _read_accelerometer(path: Path, to_ns: Callable[[str], int]) -> list[tuple[int, tuple[float, float, float]]]:
    from octolog.replay.tum import read_rows

    if not path.is_file():
        return []

    def parse(parts: list[str]) -> tuple[int, tuple[float, float, float]]:
        if len(parts) != 4:
            raise ValueError
        return to_ns(parts[0]), (float(parts[1]), float(parts[2]), float(parts[3]))

    rows = read_rows(path, parse, "timestamp ax ay az")
    return sorted(rows, key=lambda r: r[0])


def _check_size(path: Path, img: np.ndarray, intr: Intrinsics) -> None:
    if img.shape[:2] != (intr.height, intr.width):
        raise InputError(f"{path}: {img.shape[1]}x{img.shape[0]}, calibration is {intr.width}x{intr.height}")


def _intrinsics_fields(prefix: str, intr: Intrinsics, model: str = "") -> dict[str, str]:
    return {
        f"{prefix}_width": str(intr.width), f"{prefix}_height": str(intr.height),
        f"{prefix}_fx": repr(intr.fx), f"{prefix}_fy": repr(intr.fy),
        f"{prefix}_cx": repr(intr.cx), f"{prefix}_cy": repr(intr.cy),
        f"{prefix}_distortion_model": model or ("plumb_bob" if intr.distortion else "none"),
        f"{prefix}_distortion": " ".join(repr(float(x)) for x in intr.distortion),
    }


# --- bags ---------------------------------------------------------------------------------------

# rosbags raises these (and plain struct/sqlite/zstd errors) for damaged or unreadable bags.
def _bag_error_types() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    return (AnyReaderError, Reader1Error, Reader2Error, SerdeError, TypesysError, struct.error, sqlite3.Error,
            OSError, EOFError, ValueError, KeyError, IndexError, AssertionError)


@contextmanager
def _bag_errors(path: Path) -> Iterator[None]:
    """Turn whatever a damaged bag makes rosbags raise into one line naming the file."""
    errors = _bag_error_types()
    try:
        yield
    except OctologError:
        raise
    except errors as exc:
        text = " ".join(str(exc).split()) or type(exc).__name__
        raise InputError(f"{path}: unreadable bag (truncated or corrupt?): {text[:300]}") from None


def import_bag(path: Path, output: Path, *, overwrite: bool = False, topic_map: dict[str, str] | None = None,
               compression: str = "zstd", depth_scale_m: float | None = None,
               progress: Callable[[int], None] | None = None) -> ImportResult:
    """A ROS 1 .bag or ROS 2 bag (.db3/.mcap file or rosbag2 folder) -> MCAP; RealSense recordings
    (librealsense's /device_0/... layout) get their depth units, calibration and extrinsics extracted."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    kind = detect_kind(path)
    if kind == "tum":
        raise InputError(f"{path}: a TUM folder, not a bag")
    if depth_scale_m is not None and not depth_scale_m > 0:
        raise InputError(f"depth scale {depth_scale_m}: want > 0 metres per unit")
    store = get_typestore(Stores.ROS1_NOETIC if kind == "rosbag1" else Stores.ROS2_JAZZY)
    with _bag_errors(path):
        with AnyReader([path], default_typestore=store) as reader:
            if any(_RS_TOPIC.match(c.topic) for c in reader.connections):
                plan: _Plan = _RealSensePlan(path, reader, kind, topic_map or {})
            else:
                plan = _GenericPlan(path, reader, kind, topic_map or {})
            result = ImportResult(path, Path(output), plan.kind, skipped=plan.skipped())
            with _output(output, overwrite=overwrite, compression=compression, progress=progress) as sink:
                plan.write(sink)
                scale, scale_source = plan.depth_scale()
                if depth_scale_m is not None:
                    scale, scale_source = depth_scale_m, "given on import"
                calib = plan.calibration()
                has_depth = any(t in sink.counts for t in _DEPTH_TOPICS)
                if has_depth:
                    calib = {"depth_scale_m": repr(scale), "depth_scale_source": scale_source,
                             "depth_registered_to_color": str(ALIGNED_DEPTH.name in sink.counts).lower(), **calib}
                    result.depth_scale_m = scale
                    result.depth_registered = ALIGNED_DEPTH.name in sink.counts
                sink.metadata("calibration", calib)
                sink.metadata("source", {"kind": plan.kind, "path": str(path.resolve()), "importer": "octolog import",
                                         "topic_map": json.dumps(plan.mapping(), sort_keys=True), **plan.source_info()})
                if not sink.counts:
                    raise InputError(f"{path}: no messages on the imported topics ({', '.join(plan.mapping())})")
                result.counts = dict(sink.counts)
            result.notes.extend(plan.notes)
    return result


class _Plan:
    kind = ""
    notes: list[str]

    def write(self, sink: _Sink) -> None: ...

    def depth_scale(self) -> tuple[float, str]:
        return DEFAULT_DEPTH_SCALE_M, "default: ROS 16UC1 convention (millimetres); the bag does not say"

    def calibration(self) -> dict[str, str]:
        return {}

    def source_info(self) -> dict[str, str]:
        return {}

    def mapping(self) -> dict[str, str]:
        return {}

    def skipped(self) -> dict[str, int]:
        return {}


def _stamp(hdr: Any) -> int:
    return int(hdr.stamp.sec) * 1_000_000_000 + int(hdr.stamp.nanosec)


def _field(msg: Any, name: str) -> Any:
    """A field by its ROS 2 name, also on ROS 1 messages (CameraInfo's D, K, R, P)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def _pixels(msg: Any, topic: str) -> np.ndarray:
    """Pixels of a decoded Image or CompressedImage (RGB order for colour)."""
    try:
        if msg.__msgtype__ == COMPRESSED:
            return codec.decode_compressed_image(msg)
        if msg.encoding in ("rgba8", "bgra8"):
            raw = np.asarray(msg.data, dtype=np.uint8)
            if msg.step != msg.width * 4 or raw.size != msg.height * msg.step:
                raise InputError(f"image {msg.width}x{msg.height} {msg.encoding}: {raw.size} bytes")
            arr = raw.reshape(msg.height, msg.width, 4)[..., :3]
            return arr[..., ::-1] if msg.encoding == "bgra8" else arr
        return codec.image_array(msg)
    except InputError as exc:
        raise InputError(f"{topic}: {exc}") from None


def _layout_image(msg: Any, source_topic: str, target: str, stamp: int, frame_id: str) -> Any:
    """An Image for a layout topic: rgb8 colour or little-endian 16UC1 depth."""
    arr = _pixels(msg, source_topic)
    if target in _COLOR_TOPICS and not (arr.ndim == 3 and arr.dtype == np.uint8):
        raise InputError(f"{source_topic}: {_encoding(msg)} is not 8-bit colour; /{target} wants rgb8")
    if target in _DEPTH_TOPICS and not (arr.ndim == 2 and arr.dtype == np.uint16):
        raise InputError(f"{source_topic}: depth {_encoding(msg)} is not 16-bit integer units; /{target} wants "
                         "16UC1 (float metres would lose the sensor's units)")
    return codec.image_msg(np.ascontiguousarray(arr), stamp, frame_id)


def _encoding(msg: Any) -> str:
    return str(msg.format) if msg.__msgtype__ == COMPRESSED else str(msg.encoding)


def _copy_image(msg: Any, stamp: int) -> Any:
    return codec.msgtype(IMAGE)(header=codec.header(stamp, msg.header.frame_id), height=msg.height, width=msg.width,
                                encoding=msg.encoding, is_bigendian=msg.is_bigendian, step=msg.step,
                                data=np.asarray(msg.data, dtype=np.uint8))


def _copy_compressed(msg: Any, stamp: int) -> Any:
    return codec.msgtype(COMPRESSED)(header=codec.header(stamp, msg.header.frame_id), format=msg.format,
                                     data=np.asarray(msg.data, dtype=np.uint8))


def _copy_camera_info(msg: Any, stamp: int) -> Any:
    roi = msg.roi
    return codec.msgtype(CAMERA_INFO)(
        header=codec.header(stamp, msg.header.frame_id), height=msg.height, width=msg.width,
        distortion_model=msg.distortion_model, d=np.asarray(_field(msg, "d"), dtype=np.float64),
        k=np.asarray(_field(msg, "k"), dtype=np.float64), r=np.asarray(_field(msg, "r"), dtype=np.float64),
        p=np.asarray(_field(msg, "p"), dtype=np.float64), binning_x=msg.binning_x, binning_y=msg.binning_y,
        roi=codec.msgtype("sensor_msgs/msg/RegionOfInterest")(x_offset=roi.x_offset, y_offset=roi.y_offset,
                                                              height=roi.height, width=roi.width,
                                                              do_rectify=roi.do_rectify))


def _copy_imu(msg: Any, stamp: int, frame_id: str | None = None) -> Any:
    V, Q = codec.msgtype("geometry_msgs/msg/Vector3"), codec.msgtype("geometry_msgs/msg/Quaternion")
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    return codec.msgtype(IMU)(
        header=codec.header(stamp, msg.header.frame_id if frame_id is None else frame_id),
        orientation=Q(x=o.x, y=o.y, z=o.z, w=o.w),
        orientation_covariance=np.asarray(msg.orientation_covariance, dtype=np.float64),
        angular_velocity=V(x=w.x, y=w.y, z=w.z),
        angular_velocity_covariance=np.asarray(msg.angular_velocity_covariance, dtype=np.float64),
        linear_acceleration=V(x=a.x, y=a.y, z=a.z),
        linear_acceleration_covariance=np.asarray(msg.linear_acceleration_covariance, dtype=np.float64))


def _copy_tf(msg: Any) -> Any:
    V, Q = codec.msgtype("geometry_msgs/msg/Vector3"), codec.msgtype("geometry_msgs/msg/Quaternion")
    out = []
    for ts in msg.transforms:
        t, q = ts.transform.translation, ts.transform.rotation
        out.append(codec.msgtype("geometry_msgs/msg/TransformStamped")(
            header=codec.header(_stamp(ts.header), ts.header.frame_id), child_frame_id=ts.child_frame_id,
            transform=codec.msgtype("geometry_msgs/msg/Transform")(translation=V(x=t.x, y=t.y, z=t.z),
                                                                   rotation=Q(x=q.x, y=q.y, z=q.z, w=q.w))))
    return codec.msgtype(TF_MESSAGE)(transforms=out)


# --- other ROS bags -----------------------------------------------------------------------------


def _default_target(topic: str) -> str | None:
    """A layout topic a source topic already is, possibly under a namespace (/robot1/camera/...)."""
    name = topic.strip("/")
    for t in CAMERA_TOPICS:
        if name == t.name or name.endswith("/" + t.name):
            return t.name
    return None


class _GenericPlan(_Plan):
    """Image / CompressedImage / CameraInfo / Imu (and /tf_static) topics, mapped by name or --map."""

    def __init__(self, path: Path, reader: Any, kind: str, topic_map: dict[str, str]) -> None:
        self.path, self.reader, self.kind, self.notes = path, reader, kind, []
        conns = {c.topic: c for c in reader.connections}
        for src in topic_map:
            if src not in conns:
                raise InputError(f"{path}: --map {src}: no such topic in the bag "
                                 f"(topics of supported types: {', '.join(self._candidates()) or 'none'})")
        self.targets: dict[str, str] = {}
        for c in reader.connections:
            dst = topic_map[c.topic] if c.topic in topic_map else _default_target(c.topic)
            if dst is None:
                continue
            if c.msgtype not in BAG_TYPES and c.topic not in topic_map:
                continue  # a same-named topic of another type: not ours to guess
            if c.msgtype not in BAG_TYPES:
                raise InputError(f"{path}: {c.topic} is {c.msgtype}; importable types are {', '.join(BAG_TYPES)}")
            want = _BY_NAME[dst].msgtype if dst in _BY_NAME else c.msgtype
            if want != c.msgtype and not (want == IMAGE and c.msgtype == COMPRESSED):
                raise InputError(f"{path}: cannot map {c.topic} ({c.msgtype}) to /{dst} ({want})")
            self.targets[c.topic] = dst
        if not self.targets:
            raise InputError(f"{path}: no topic maps to the camera layout; name them with --map SOURCE=TARGET, "
                             f"e.g. --map /camera/rgb/image_color={COLOR.name} (topics of supported types: "
                             f"{', '.join(self._candidates()) or 'none'})")
        dup = {d for d in self.targets.values() if list(self.targets.values()).count(d) > 1}
        if dup:
            raise InputError(f"{path}: several topics map to /{sorted(dup)[0]}")
        self.conns = [conns[t] for t in self.targets]

    def _candidates(self) -> list[str]:
        return sorted(c.topic for c in self.reader.connections if c.msgtype in BAG_TYPES)

    def write(self, sink: _Sink) -> None:
        for conn, bag_ns, raw in self.reader.messages(connections=self.conns):
            msg = self.reader.deserialize(raw, conn.msgtype)
            dst = self.targets[conn.topic]
            if conn.msgtype == TF_MESSAGE:
                stamps = [_stamp(t.header) for t in msg.transforms]
                stamp = min(stamps) if stamps and min(stamps) > 0 else bag_ns
                sink.put(dst, TF_MESSAGE, _copy_tf(msg), stamp)
                continue
            stamp = _stamp(msg.header) or bag_ns  # no sensor stamp: the bag's receive time
            if dst in _COLOR_TOPICS or dst in _DEPTH_TOPICS:
                out, typ = _layout_image(msg, conn.topic, dst, stamp, msg.header.frame_id), IMAGE
            elif conn.msgtype == IMAGE:
                out, typ = _copy_image(msg, stamp), IMAGE
            elif conn.msgtype == COMPRESSED:
                want = _BY_NAME[dst].msgtype if dst in _BY_NAME else COMPRESSED
                if want == IMAGE:
                    out, typ = codec.image_msg(_pixels(msg, conn.topic), stamp, msg.header.frame_id), IMAGE
                else:
                    out, typ = _copy_compressed(msg, stamp), COMPRESSED
            elif conn.msgtype == CAMERA_INFO:
                out, typ = _copy_camera_info(msg, stamp), CAMERA_INFO
            else:
                out, typ = _copy_imu(msg, stamp), IMU
            sink.put(dst, typ, out, stamp)
        if any(d in _DEPTH_TOPICS for d in self.targets.values()):
            self.notes.append(f"depth scale: the bag does not say; {DEFAULT_DEPTH_SCALE_M} m per unit assumed "
                              "(ROS 16UC1 convention) unless given")

    def mapping(self) -> dict[str, str]:
        return dict(self.targets)

    def skipped(self) -> dict[str, int]:
        return {c.topic: c.msgcount for c in self.reader.connections if c.topic not in self.targets}


# --- RealSense recordings -----------------------------------------------------------------------

# librealsense's layout: /device_0/sensor_<n>/<Stream>_<index>/<what>, options under /option/<Name>/value.
_RS_TOPIC = re.compile(r"^/device_\d+/sensor_\d+/(?P<stream>[A-Za-z]+)_(?P<index>\d+)/(?P<what>.+)$")
_RS_OPTION = re.compile(r"^/device_\d+/sensor_\d+/option/(?P<name>[^/]+)/value$")
_RS_DATA = ("image/data", "image/data/compressed", "image/data/compressedDepth", "imu/data")
_RS_INFO = ("info/camera_info", "image/camera_info")  # ROS 1 .bag, librealsense 2.59 .db3
_RS_META = ("image/metadata", "imu/metadata")
# Default output per stream: (data topic, camera_info topic, frame id).
_RS_STREAMS: dict[str, tuple[Topic, Topic | None, str]] = {
    "Color_0": (COLOR, COLOR_INFO, COLOR_FRAME),
    "Depth_0": (DEPTH, DEPTH_INFO, DEPTH_FRAME),
    "Accel_0": (ACCEL, None, ACCEL_FRAME),
    "Gyro_0": (GYRO, None, GYRO_FRAME),
}
_FRAME_FOR = {COLOR.name: COLOR_FRAME, ALIGNED_DEPTH.name: COLOR_FRAME, DEPTH.name: DEPTH_FRAME,
              ACCEL.name: ACCEL_FRAME, GYRO.name: GYRO_FRAME}


def _kv(text: str) -> dict[str, str]:
    """librealsense 2.59's 'key=value;key=value' strings."""
    out = {}
    for part in text.split(";"):
        k, sep, v = part.partition("=")
        if sep:
            out[k.strip()] = v.strip()
    return out


def _float32_value(x: float) -> float:
    """The decimal a float32 option value was set as (Depth Units 0.0010000000474974513 -> 0.001)."""
    return float(str(np.float32(x)))


class _RealSensePlan(_Plan):
    """librealsense recordings: ROS 1 .bag (file format 2-4) and librealsense 2.59's ROS 2 .db3."""

    def __init__(self, path: Path, reader: Any, kind: str, topic_map: dict[str, str]) -> None:
        self.path, self.reader, self.notes = path, reader, []
        self.ros2 = kind == "rosbag2"
        self.kind = "realsense-db3" if self.ros2 else "realsense-bag"
        self.data: dict[str, tuple[str, str]] = {}  # data topic -> (stream, target)
        self.info_conn: dict[str, Any] = {}  # stream -> camera_info connection
        self.meta_conns: dict[int, tuple[Any, str]] = {}  # connection id -> (connection, stream)
        self.tf_conns: dict[int, tuple[Any, str]] = {}
        self.option_conns: list[Any] = []
        self.device_conns: list[Any] = []
        conns = {c.topic: c for c in reader.connections}
        for src in topic_map:
            if src not in conns:
                raise InputError(f"{path}: --map {src}: no such topic in the bag")
        for c in reader.connections:
            m = _RS_TOPIC.match(c.topic)
            if m is None:
                if _RS_OPTION.match(c.topic):
                    self.option_conns.append(c)
                elif c.topic in ("/device_0/info", "/file_version"):
                    self.device_conns.append(c)
                continue
            stream = f"{m['stream']}_{m['index']}"
            what = m["what"]
            if what in _RS_DATA and c.msgtype in (IMAGE, COMPRESSED, IMU):
                default = _RS_STREAMS.get(stream)
                target = topic_map.get(c.topic, default[0].name if default else None)
                if target:
                    self.data[c.topic] = (stream, target.strip("/"))
            elif what in _RS_INFO and c.msgtype == CAMERA_INFO:
                self.info_conn[stream] = c
            elif what in _RS_META:
                self.meta_conns[c.id] = (c, stream)
            elif what.startswith("tf/"):
                self.tf_conns[c.id] = (c, stream)
        if not self.data:
            raise InputError(f"{path}: RealSense recording without colour, depth or IMU data")
        for src in topic_map:
            if src not in self.data:
                raise InputError(f"{path}: --map {src}: in a RealSense recording only image and IMU data topics "
                                 f"(.../image/data, .../imu/data) can be mapped")
        targets = [t for _, t in self.data.values()]
        if len(set(targets)) != len(targets):
            raise InputError(f"{path}: several streams map to the same topic ({', '.join(sorted(targets))})")
        self._scan()

    def _scan(self) -> None:
        """Read the small topics: calibration, depth units, extrinsics, device info, frame timestamps."""
        r = self.reader
        self.intrinsics: dict[str, tuple[Intrinsics, str]] = {}
        for stream, c in self.info_conn.items():
            for _, _, raw in r.messages(connections=[c]):
                msg = r.deserialize(raw, c.msgtype)
                if stream in self.intrinsics:
                    break
                self.intrinsics[stream] = (codec.intrinsics_from(_CameraInfoView(msg)), str(msg.distortion_model))
        self.depth_units: float | None = None
        for c in self.option_conns:
            name = _RS_OPTION.match(c.topic)["name"].replace("_", " ")  # type: ignore[index]
            if name != "Depth Units":
                continue
            for _, _, raw in r.messages(connections=[c]):
                msg = r.deserialize(raw, c.msgtype)
                value = float(msg.data) if c.msgtype != "std_msgs/msg/Float32" else _float32_value(msg.data)
                if value > 0:
                    self.depth_units = value
        # Extrinsics of each stream from the group's reference stream: p_stream = R p_ref + t.
        self.stream_from_ref: dict[str, np.ndarray] = {}
        for c, stream in self.tf_conns.values():
            for _, _, raw in r.messages(connections=[c]):
                self.stream_from_ref[stream] = self._transform(r.deserialize(raw, c.msgtype))
        self.device: dict[str, str] = {}
        for c in self.device_conns:
            for _, _, raw in r.messages(connections=[c]):
                msg = r.deserialize(raw, c.msgtype)
                if c.topic == "/file_version":
                    self.device["file_version"] = str(msg.data)
                elif hasattr(msg, "key"):
                    self.device[str(msg.key)] = str(msg.value)
                else:
                    self.device.update(_kv(str(msg.data)))
        # librealsense 2.59 stamps .db3 headers with recording time; the frame's own timestamp (ms, in
        # its clock domain) is in the metadata message written at the same bag time.
        self.frame_stamps: dict[tuple[str, int], int] = {}
        self.meta_units: float | None = None
        if self.ros2:
            for c, bag_ns, raw in r.messages(connections=[c for c, _ in self.meta_conns.values()]):
                msg = r.deserialize(raw, c.msgtype)
                if not hasattr(msg, "data"):
                    continue
                kv = _kv(str(msg.data))
                try:
                    if "timestamp" in kv:
                        ns = Decimal(kv["timestamp"]) * 1_000_000
                        self.frame_stamps[(self.meta_conns[c.id][1], bag_ns)] = int(ns.to_integral_value())
                    if self.meta_units is None and "depth_units" in kv and float(kv["depth_units"]) > 0:
                        self.meta_units = float(kv["depth_units"])
                except (InvalidOperation, ValueError):
                    raise InputError(f"{self.path}: {c.topic}: malformed frame metadata {msg.data!r}") from None

    def _transform(self, msg: Any) -> np.ndarray:
        if hasattr(msg, "translation"):  # geometry_msgs/Transform (ROS 1 bags), the rs2_extrinsics as is
            t, q = msg.translation, msg.rotation
            return pose_to_matrix(np.array([t.x, t.y, t.z]), np.array([q.x, q.y, q.z, q.w]))
        kv = _kv(str(msg.data))  # librealsense 2.59: "rotation=<9, column-major>;translation=<3>"
        try:
            rot = np.array([float(x) for x in kv["rotation"].split(",")]).reshape(3, 3).T
            T = np.eye(4)
            T[:3, :3] = rot
            T[:3, 3] = [float(x) for x in kv["translation"].split(",")]
        except (KeyError, ValueError):
            raise InputError(f"{self.path}: malformed extrinsics {msg.data!r}") from None
        return T

    def write(self, sink: _Sink) -> None:
        r = self.reader
        conns = [c for c in r.connections if c.topic in self.data]
        first = None
        for c, bag_ns, raw in r.messages(connections=conns):
            stream, dst = self.data[c.topic]
            msg = r.deserialize(raw, c.msgtype)
            stamp = self.frame_stamps.get((stream, bag_ns)) if self.ros2 else None
            if stamp is None:
                stamp = _stamp(msg.header) or bag_ns
            first = stamp if first is None else min(first, stamp)
            frame_id = _FRAME_FOR.get(dst, msg.header.frame_id)
            if c.msgtype == IMU:
                sink.put(dst, IMU, _copy_imu(msg, stamp, frame_id), stamp)
                continue
            if dst in _COLOR_TOPICS or dst in _DEPTH_TOPICS:
                out = _layout_image(msg, c.topic, dst, stamp, frame_id)
            else:
                out = codec.image_msg(np.ascontiguousarray(_pixels(msg, c.topic)), stamp, frame_id)
            sink.put(dst, IMAGE, out, stamp)
            info = _INFO_FOR.get(dst)
            if stream in self.intrinsics and info is not None:
                intr, model = self.intrinsics[stream]
                sink.put(info.name, info.msgtype, self._info_msg(intr, model, stamp, frame_id), stamp)
            elif info is not None and stream not in self.intrinsics:
                raise InputError(f"{self.path}: {c.topic}: no camera_info for stream {stream} (missing calibration)")
        tfs = self._tf_static()
        if tfs and first is not None:
            sink.put(TF_STATIC.name, TF_STATIC.msgtype, codec.tf_static_msg(tfs, first), first)

    @staticmethod
    def _info_msg(intr: Intrinsics, model: str, stamp: int, frame_id: str) -> Any:
        msg = codec.camera_info_msg(intr, stamp, frame_id)
        # Brown-Conrady is ROS's plumb_bob; keep other librealsense models' names (their coefficients differ).
        if model and model not in ("Brown Conrady", "plumb_bob", "None"):
            msg.distortion_model = model
        return msg

    def _frames_of(self) -> dict[str, str]:
        return {stream: _FRAME_FOR.get(dst, stream) for stream, dst in self.data.values()}

    def _tf_static(self) -> list[tuple[str, str, np.ndarray]]:
        """depth_optical <- other streams, from the recorded extrinsics (when Depth_0 has them)."""
        frames = self._frames_of()
        if "Depth_0" not in self.stream_from_ref or "Depth_0" not in frames:
            return []
        depth_from_ref = self.stream_from_ref["Depth_0"]
        out = []
        for stream, frame in sorted(frames.items()):
            if stream == "Depth_0" or stream not in self.stream_from_ref or frame == frames["Depth_0"]:
                continue
            out.append((frames["Depth_0"], frame, depth_from_ref @ invert(self.stream_from_ref[stream])))
        return out

    def depth_scale(self) -> tuple[float, str]:
        if self.depth_units is not None:
            return self.depth_units, "RealSense 'Depth Units' option recorded in the bag"
        if self.meta_units is not None:
            return self.meta_units, "RealSense frame metadata depth_units"
        return super().depth_scale()

    def calibration(self) -> dict[str, str]:
        out: dict[str, str] = {}
        names = {"Color_0": "color", "Depth_0": "depth"}
        for stream, (intr, model) in sorted(self.intrinsics.items()):
            if stream in names:
                out.update(_intrinsics_fields(names[stream], intr, model))
        out["intrinsics_source"] = "RealSense camera_info recorded in the bag"
        if "Depth_0" in self.stream_from_ref and "Color_0" in self.stream_from_ref:
            T = self.stream_from_ref["Color_0"] @ invert(self.stream_from_ref["Depth_0"])
            out["color_from_depth"] = " ".join(repr(float(x)) for x in T[:3, :4].reshape(-1))
            out["color_from_depth_layout"] = "3x4 row-major [R | t], metres: p_color = R p_depth + t"
        return out

    def source_info(self) -> dict[str, str]:
        return {f"device_{k.lower().replace(' ', '_')}": v for k, v in sorted(self.device.items())
                if k != "file_version"} | ({"file_version": self.device["file_version"]}
                                           if "file_version" in self.device else {})

    def mapping(self) -> dict[str, str]:
        return {src: dst for src, (_, dst) in self.data.items()}

    def skipped(self) -> dict[str, int]:
        return {c.topic: c.msgcount for c in self.reader.connections
                if c.topic not in self.data and c.msgtype in (IMAGE, COMPRESSED, IMU)}


class _CameraInfoView:
    """ROS 1 and ROS 2 CameraInfo alike for codec.intrinsics_from (k, d lower-case)."""

    def __init__(self, msg: Any) -> None:
        self.width, self.height = msg.width, msg.height
        self.k, self.d = _field(msg, "k"), _field(msg, "d")
