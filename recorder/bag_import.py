"""ROS 1 .bag and ROS 2 bags (.db3/.mcap file or rosbag2 folder) -> MCAP in the recorder's layout:
RealSense recordings through their own plan, any other bag's Image/CompressedImage/CameraInfo/Imu
(and /tf_static) topics mapped by name or --map."""

from __future__ import annotations

import json
import sqlite3
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Reader1Error
from rosbags.rosbag2 import ReaderError as Reader2Error
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore

from octolog.kit.errors import InputError, OctologError
from octolog.recorder.bag_messages import (
    BAG_TYPES,
    CAMERA_INFO,
    COLOR_TOPICS,
    COMPRESSED,
    DEPTH_TOPICS,
    IMAGE,
    IMU,
    LAYOUT_BY_NAME,
    TF_MESSAGE,
    BagPlan,
    copy_camera_info,
    copy_compressed,
    copy_image,
    copy_imu,
    copy_tf,
    header_stamp_ns,
    layout_image,
    pixels,
)
from octolog.recorder.import_output import DEFAULT_DEPTH_SCALE_M, ImportResult, ImportSink, detect_kind, open_output
from octolog.recorder.realsense_bag import RS_TOPIC, RealSenseBagPlan
from octolog.schemas import sensormsgs
from octolog.schemas.topics import ALIGNED_DEPTH, CAMERA_TOPICS, COLOR

# rosbags raises these (and plain struct/sqlite/zstd errors) for damaged or unreadable bags.
BAG_ERRORS: tuple[type[BaseException], ...] = (
    AnyReaderError, Reader1Error, Reader2Error, SerdeError, TypesysError, struct.error, sqlite3.Error,
    OSError, EOFError, ValueError, KeyError, IndexError, AssertionError)


@contextmanager
def _bag_errors(path: Path) -> Iterator[None]:
    """Turn whatever a damaged bag makes rosbags raise into one line naming the file."""
    try:
        yield
    except OctologError:
        raise
    except BAG_ERRORS as exc:
        text = " ".join(str(exc).split()) or type(exc).__name__
        raise InputError(f"{path}: unreadable bag (truncated or corrupt?): {text[:300]}") from None


def import_bag(path: Path, output: Path, *, overwrite: bool = False, topic_map: dict[str, str] | None = None,
               compression: str = "zstd", depth_scale_m: float | None = None,
               progress: Callable[[int], None] | None = None) -> ImportResult:
    """A ROS 1 .bag or ROS 2 bag (.db3/.mcap file or rosbag2 folder) -> MCAP; RealSense recordings
    (librealsense's /device_0/... layout) get their depth units, calibration and extrinsics extracted."""
    path = Path(path)
    kind = detect_kind(path)
    if kind == "tum":
        raise InputError(f"{path}: a TUM folder, not a bag")
    if depth_scale_m is not None and not depth_scale_m > 0:
        raise InputError(f"depth scale {depth_scale_m}: want > 0 metres per unit")
    store = get_typestore(Stores.ROS1_NOETIC if kind == "rosbag1" else Stores.ROS2_JAZZY)
    with _bag_errors(path):
        with AnyReader([path], default_typestore=store) as reader:
            if any(RS_TOPIC.match(c.topic) for c in reader.connections):
                plan: BagPlan = RealSenseBagPlan(path, reader, kind, topic_map or {})
            else:
                plan = _GenericPlan(path, reader, kind, topic_map or {})
            result = ImportResult(path, Path(output), plan.kind, skipped=plan.skipped())
            with open_output(output, overwrite=overwrite, compression=compression, progress=progress) as sink:
                plan.write(sink)
                scale, scale_source = plan.depth_scale()
                if depth_scale_m is not None:
                    scale, scale_source = depth_scale_m, "given on import"
                calib = plan.calibration()
                has_depth = any(t in sink.counts for t in DEPTH_TOPICS)
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


# --- other ROS bags -----------------------------------------------------------------------------


def _default_target(topic: str) -> str | None:
    """A layout topic a source topic already is, possibly under a namespace (/robot1/camera/...)."""
    name = topic.strip("/")
    for t in CAMERA_TOPICS:
        if name == t.name or name.endswith("/" + t.name):
            return t.name
    return None


class _GenericPlan(BagPlan):
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
            want = LAYOUT_BY_NAME[dst].msgtype if dst in LAYOUT_BY_NAME else c.msgtype
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

    def write(self, sink: ImportSink) -> None:
        for conn, bag_ns, raw in self.reader.messages(connections=self.conns):
            msg = self.reader.deserialize(raw, conn.msgtype)
            dst = self.targets[conn.topic]
            if conn.msgtype == TF_MESSAGE:
                stamps = [header_stamp_ns(t.header) for t in msg.transforms]
                stamp = min(stamps) if stamps and min(stamps) > 0 else bag_ns
                sink.put(dst, TF_MESSAGE, copy_tf(msg), stamp)
                continue
            stamp = header_stamp_ns(msg.header) or bag_ns  # no sensor stamp: the bag's receive time
            if dst in COLOR_TOPICS or dst in DEPTH_TOPICS:
                out, typ = layout_image(msg, conn.topic, dst, stamp, msg.header.frame_id), IMAGE
            elif conn.msgtype == IMAGE:
                out, typ = copy_image(msg, stamp), IMAGE
            elif conn.msgtype == COMPRESSED:
                want = LAYOUT_BY_NAME[dst].msgtype if dst in LAYOUT_BY_NAME else COMPRESSED
                if want == IMAGE:
                    out, typ = sensormsgs.image_msg(pixels(msg, conn.topic), stamp, msg.header.frame_id), IMAGE
                else:
                    out, typ = copy_compressed(msg, stamp), COMPRESSED
            elif conn.msgtype == CAMERA_INFO:
                out, typ = copy_camera_info(msg, stamp), CAMERA_INFO
            else:
                out, typ = copy_imu(msg, stamp), IMU
            sink.put(dst, typ, out, stamp)
        if any(d in DEPTH_TOPICS for d in self.targets.values()):
            self.notes.append(f"depth scale: the bag does not say; {DEFAULT_DEPTH_SCALE_M} m per unit assumed "
                              "(ROS 16UC1 convention) unless given")

    def mapping(self) -> dict[str, str]:
        return dict(self.targets)

    def skipped(self) -> dict[str, int]:
        return {c.topic: c.msgcount for c in self.reader.connections if c.topic not in self.targets}
