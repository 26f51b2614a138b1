"""The session log in standard ROS 2 types: how a wire message of an octolog type is stored, and back.

The bus carries a few octolog_msgs types: an RGB-D pair with its calibration in one message (so a
frame never arrives half), a keyframe, the tracker's status, end-of-stream counts. Viewers and tools
(Rerun's MCAP loader, Foxglove, rosbags, `ros2 bag`) know only standard types, so the session log
stores each such message as standard-typed parts, written one after the other:

- its images, camera info and poses as what they are: `sensor_msgs/Image` or `CompressedImage` on
  the realsense-ros names the recorder writes (`camera/color/image_raw[/compressed]`,
  `camera/aligned_depth_to_color/image_raw[/compressed]`, `camera/color/camera_info`), a keyframe's
  on `tracker/keyframe/...`, a keyframe's pose as `geometry_msgs/PoseStamped`, corrected keyframe
  poses as `geometry_msgs/PoseArray`; the images' bytes are the wire's, never re-encoded;
- last, on the wire topic's own name, a `diagnostic_msgs/DiagnosticArray` with the message's header
  and one status: name = the wire topic, message = the wire type, `values` = every other field
  (sequence numbers, ids, the depth scale, counts), JSON-encoded (floats by their shortest repr,
  which reads back to the same double). The tracker's status shows as such in Foxglove's
  diagnostics panel, with a level (OK, WARN for INIT/SKIPPED, ERROR for LOST).

`join` rebuilds the wire message from its parts, byte for byte (the logger checks the first message
of every topic, tests/schemas/test_logview.py all of them), so a replay from the log publishes exactly what
the live run published. Messages of standard types are stored as they are.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.imu import IMU_NOISE_FIELDS
from octolog.schemas import codec
from octolog.schemas.msgtypes import DiagnosticArray

DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED, POSE_ARRAY = "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseArray"


@dataclass(frozen=True)
class Part:
    field: str  # the wire message's field
    topic: str  # the log topic it is stored on
    msgtype: str  # its standard type there


# wire type -> its parts (the remaining fields go to the DiagnosticArray on the wire topic)
_CAMERA = "camera/color/camera_info"
PARTS: dict[str, tuple[Part, ...]] = {
    "octolog_msgs/msg/RgbdFrame": (
        Part("color", "camera/color/image_raw", IMAGE),
        Part("depth", "camera/aligned_depth_to_color/image_raw", IMAGE),
        Part("camera_info", _CAMERA, CAMERA_INFO)),
    "octolog_msgs/msg/CompressedRgbdFrame": (
        Part("color", "camera/color/image_raw/compressed", COMPRESSED),
        Part("depth", "camera/aligned_depth_to_color/image_raw/compressed", COMPRESSED),
        Part("camera_info", _CAMERA, CAMERA_INFO)),
    "octolog_msgs/msg/Keyframe": (
        Part("color", "tracker/keyframe/color/image_raw", IMAGE),
        Part("depth", "tracker/keyframe/depth/image_raw", IMAGE),
        Part("camera_info", "tracker/keyframe/camera_info", CAMERA_INFO),
        Part("world_from_camera", "tracker/keyframe/pose", POSE_STAMPED)),
    "octolog_msgs/msg/CompressedKeyframe": (
        Part("color", "tracker/keyframe/color/image_raw/compressed", COMPRESSED),
        Part("depth", "tracker/keyframe/depth/image_raw/compressed", COMPRESSED),
        Part("camera_info", "tracker/keyframe/camera_info", CAMERA_INFO),
        Part("world_from_camera", "tracker/keyframe/pose", POSE_STAMPED)),
    "octolog_msgs/msg/KeyframePoses": (Part("world_from_camera", "tracker/keyframe_poses/poses", POSE_ARRAY),),
}
# Fields added to a wire type after logs of it were written, and what an older log's message reads as
ADDED_FIELDS = {("octolog_msgs/msg/TrackingStatus", "map_moved_m"): "0.0",
                ("octolog_msgs/msg/TrackingStatus", "relocalised"): "false",
                ("octolog_msgs/msg/TrackingStatus", "imu_gyro_count"): "0",
                ("octolog_msgs/msg/TrackingStatus", "imu_accel_count"): "0",
                ("octolog_msgs/msg/Keyframe", "depth_inverse_offset"): "0.0",
                ("octolog_msgs/msg/CompressedKeyframe", "depth_inverse_offset"): "0.0",
                ("octolog_msgs/msg/KeyframePoses", "depth_inverse_offset"): "0.0",
                ("octolog_msgs/msg/CameraProperties", "depth_baseline_m"): "0.0",
                ("octolog_msgs/msg/CameraProperties", "depth_focal_px"): "0.0",
                ("octolog_msgs/msg/CameraProperties", "depth_disparity_sigma_px"): "0.0",
                **{("octolog_msgs/msg/CameraProperties", k): "0.0" for k in IMU_NOISE_FIELDS}}
# TrackingStatus.state -> diagnostic level (OK=0, WARN=1, ERROR=2): INIT, SKIPPED and INERTIAL warn, LOST is an error
_STATE_LEVEL = {0: 1, 1: 0, 2: 2, 3: 1, 4: 1}


def is_split(msgtype: str) -> bool:
    """A wire type the log stores as standard parts (every octolog_msgs type)."""
    return msgtype.startswith(codec.OWN_PACKAGE + "/")


def part_topics(msgtype: str) -> tuple[str, ...]:
    return tuple(p.topic for p in PARTS.get(msgtype, ()))


@cache
def _residual_fields(msgtype: str) -> tuple[tuple[str, str, bool], ...]:
    """(field, base type, is a sequence) of the fields a DiagnosticArray carries, in message order."""
    parts = {p.field for p in PARTS.get(msgtype, ())}
    out = []
    for name, (node, spec) in codec.typestore().fielddefs[msgtype][1]:
        if name == "header" or name in parts:
            continue
        if node.name == "BASE":
            out.append((name, spec[0], False))
        elif node.name == "SEQUENCE" and spec[0][0].name == "BASE":
            out.append((name, spec[0][1][0], True))
        else:
            raise TypeError(f"{msgtype}.{name}: a nested field without a standard part")
    return tuple(out)


def _plain(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value.item() if isinstance(value, np.generic) else value


def split(topic: str, msgtype: str, payload: bytes) -> list[tuple[str, str, bytes]]:
    """(log topic, standard type, CDR bytes) to write, in order; the DiagnosticArray comes last."""
    if not is_split(msgtype):
        return [(topic, msgtype, payload)]
    msg = codec.decode(payload, msgtype)
    out = []
    for p in PARTS.get(msgtype, ()):
        value = getattr(msg, p.field)
        if p.msgtype == POSE_STAMPED:
            value = codec.msgtype(POSE_STAMPED)(header=msg.header, pose=value)
        elif p.msgtype == POSE_ARRAY:
            value = codec.msgtype(POSE_ARRAY)(header=msg.header, poses=value)
        out.append((p.topic, p.msgtype, codec.encode(value, p.msgtype)))
    KeyValue = codec.msgtype("diagnostic_msgs/msg/KeyValue")
    values = [KeyValue(key=name, value=json.dumps(_plain(getattr(msg, name))))
              for name, _, _ in _residual_fields(msgtype)]
    level = _STATE_LEVEL.get(int(msg.state), 0) if hasattr(msg, "state") else 0
    status = codec.msgtype("diagnostic_msgs/msg/DiagnosticStatus")(
        level=level, name=topic, message=msgtype, hardware_id="octolog", values=values)
    out.append((topic, DIAGNOSTICS, codec.encode(codec.msgtype(DIAGNOSTICS)(header=msg.header, status=[status]),
                                                 DIAGNOSTICS)))
    return out


def wire_type(diagnostics: DiagnosticArray) -> str | None:
    """The wire type a logged DiagnosticArray stands for, or None (a DiagnosticArray of its own)."""
    if len(diagnostics.status) != 1:
        return None
    msgtype = str(diagnostics.status[0].message)
    return msgtype if is_split(msgtype) and msgtype in codec.typestore().types else None


_DTYPES = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
           "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
           "float32": np.float32, "float64": np.float64}


def _value(raw: str, base: str, sequence: bool) -> object:
    value = json.loads(raw)
    if sequence:
        return list(map(str, value)) if base == "string" else np.asarray(value, dtype=_DTYPES[base])
    if base == "string":
        return str(value)
    if base == "bool":
        return bool(value)
    return float(value) if base.startswith("float") else int(value)


def join(msgtype: str, diagnostics: bytes, parts: dict[str, bytes]) -> bytes:
    """The wire message's CDR bytes from its DiagnosticArray and its parts (log topic -> bytes)."""
    diag = codec.decode(diagnostics, DIAGNOSTICS)
    fields: dict[str, object] = {"header": diag.header}
    for p in PARTS.get(msgtype, ()):
        if p.topic not in parts:
            raise InputError(f"a logged {msgtype} without its /{p.topic} part")
        value = codec.decode(parts[p.topic], p.msgtype)
        fields[p.field] = value.pose if p.msgtype == POSE_STAMPED else value.poses if p.msgtype == POSE_ARRAY else value
    values = {kv.key: kv.value for kv in diag.status[0].values}
    try:
        for name, base, sequence in _residual_fields(msgtype):
            raw = values[name] if name in values else ADDED_FIELDS[(msgtype, name)]
            fields[name] = _value(raw, base, sequence)
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(f"a logged {msgtype} with an unreadable field: {type(exc).__name__}: {exc}") from None
    return codec.encode(codec.msgtype(msgtype)(**fields), msgtype)
