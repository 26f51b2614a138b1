"""librealsense recordings (ROS 1 .bag, librealsense 2.59's ROS 2 .db3): device data topics into the
recorder's layout, with the depth units, calibration and extrinsics the recording holds."""

from __future__ import annotations

import re
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics, invert, pose_to_matrix
from octolog.recorder.bag_messages import (
    CAMERA_INFO,
    COLOR_TOPICS,
    COMPRESSED,
    DEPTH_TOPICS,
    IMAGE,
    IMU,
    BagPlan,
    copy_imu,
    header_stamp_ns,
    layout_image,
    pixels,
    ros_field,
)
from octolog.recorder.import_output import (
    ACCEL_FRAME,
    COLOR_FRAME,
    DEPTH_FRAME,
    GYRO_FRAME,
    ImportSink,
    intrinsics_fields,
)
from octolog.schemas import posemsgs, sensormsgs
from octolog.schemas.topics import (
    ACCEL,
    ALIGNED_DEPTH,
    ALIGNED_DEPTH_INFO,
    COLOR,
    COLOR_INFO,
    DEPTH,
    DEPTH_INFO,
    GYRO,
    TF_STATIC,
    Topic,
)

# the camera_info topic that goes with each layout image topic
_INFO_FOR = {COLOR.name: COLOR_INFO, ALIGNED_DEPTH.name: ALIGNED_DEPTH_INFO, DEPTH.name: DEPTH_INFO}

# librealsense's layout: /device_0/sensor_<n>/<Stream>_<index>/<what>, options under /option/<Name>/value.
RS_TOPIC = re.compile(r"^/device_\d+/sensor_\d+/(?P<stream>[A-Za-z]+)_(?P<index>\d+)/(?P<what>.+)$")
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


class RealSenseBagPlan(BagPlan):
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
            m = RS_TOPIC.match(c.topic)
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
                self.intrinsics[stream] = (sensormsgs.intrinsics_from(_CameraInfoView(msg)), str(msg.distortion_model))
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

    def write(self, sink: ImportSink) -> None:
        r = self.reader
        conns = [c for c in r.connections if c.topic in self.data]
        first = None
        for c, bag_ns, raw in r.messages(connections=conns):
            stream, dst = self.data[c.topic]
            msg = r.deserialize(raw, c.msgtype)
            stamp = self.frame_stamps.get((stream, bag_ns)) if self.ros2 else None
            if stamp is None:
                stamp = header_stamp_ns(msg.header) or bag_ns
            first = stamp if first is None else min(first, stamp)
            frame_id = _FRAME_FOR.get(dst, msg.header.frame_id)
            if c.msgtype == IMU:
                sink.put(dst, IMU, copy_imu(msg, stamp, frame_id), stamp)
                continue
            if dst in COLOR_TOPICS or dst in DEPTH_TOPICS:
                out = layout_image(msg, c.topic, dst, stamp, frame_id)
            else:
                out = sensormsgs.image_msg(np.ascontiguousarray(pixels(msg, c.topic)), stamp, frame_id)
            sink.put(dst, IMAGE, out, stamp)
            info = _INFO_FOR.get(dst)
            if stream in self.intrinsics and info is not None:
                intr, model = self.intrinsics[stream]
                sink.put(info.name, info.msgtype, self._info_msg(intr, model, stamp, frame_id), stamp)
            elif info is not None and stream not in self.intrinsics:
                raise InputError(f"{self.path}: {c.topic}: no camera_info for stream {stream} (missing calibration)")
        tfs = self._tf_static()
        if tfs and first is not None:
            sink.put(TF_STATIC.name, TF_STATIC.msgtype, posemsgs.tf_msg(tfs, first), first)

    @staticmethod
    def _info_msg(intr: Intrinsics, model: str, stamp: int, frame_id: str) -> Any:
        msg = sensormsgs.camera_info_msg(intr, stamp, frame_id)
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
                out.update(intrinsics_fields(names[stream], intr, model))
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
    """ROS 1 and ROS 2 CameraInfo alike for sensormsgs.intrinsics_from (k, d lower-case)."""

    def __init__(self, msg: Any) -> None:
        self.width, self.height = msg.width, msg.height
        self.k, self.d = ros_field(msg, "k"), ros_field(msg, "d")
