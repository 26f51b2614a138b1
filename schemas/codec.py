"""The typed codec: ROS 2 messages through rosbags' type store, CDR on the wire and in MCAP.

Our own types are `.msg` files beside this module; a schema change is a new type, never an edit.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import zstandard
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from octolog.kit.errors import ConfigError, InputError
from octolog.kit.geometry import EncodedRgbd, Intrinsics, RgbdFrame, matrix_to_pose, pose_to_matrix
from octolog.schemas.imageheaders import ZSTD_DEPTH_HEADER, ZSTD_DEPTH_MAGIC, declared_size

MSG_DIR = Path(__file__).with_name("msg")
OWN_PACKAGE = "octolog_msgs"
# Types from outside ROS 2's core that we vendor as .msg text.
VENDORED = {"Octomap": "octomap_msgs"}


@cache
def typestore() -> Any:
    """ROS 2 (Jazzy) type store with octolog's own message types registered."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for path in sorted(MSG_DIR.glob("*.msg")):
        pkg = VENDORED.get(path.stem, OWN_PACKAGE)
        types.update(get_types_from_msg(path.read_text(), f"{pkg}/msg/{path.stem}"))
    store.register(types)
    return store


def msgtype(name: str) -> Any:
    return typestore().types[name]


def encode(msg: Any, typename: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, typename))


def decode(data: bytes | memoryview, typename: str) -> Any:
    try:
        return typestore().deserialize_cdr(data, typename)
    except Exception as exc:  # rosbags raises several types for short or garbled buffers
        raise InputError(f"cannot decode {typename}: {exc}") from None


def msgdef(typename: str) -> str:
    """The ros2msg schema text MCAP files carry for a type."""
    return typestore().generate_msgdef(typename, ros_version=2)[0]


# --- builders and readers -------------------------------------------------------------------


def header(stamp_ns: int, frame_id: str = "") -> Any:
    Time = msgtype("builtin_interfaces/msg/Time")
    Header = msgtype("std_msgs/msg/Header")
    return Header(stamp=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000), frame_id=frame_id)


def stamp_ns(hdr: Any) -> int:
    return int(hdr.stamp.sec) * 1_000_000_000 + int(hdr.stamp.nanosec)


_ENCODINGS = {("uint8", 3): "rgb8", ("uint16", 1): "16UC1", ("uint8", 1): "mono8", ("float32", 1): "32FC1"}
_DTYPES = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "16UC1": (np.uint16, 1), "mono16": (np.uint16, 1),
           "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "32FC1": (np.float32, 1)}
IMAGE_ENCODINGS = _DTYPES  # sensor_msgs/Image encodings taken: numpy dtype, channels


def image_msg(array: np.ndarray, stamp: int, frame_id: str) -> Any:
    channels = 1 if array.ndim == 2 else array.shape[2]
    encoding = _ENCODINGS[(array.dtype.name, channels)]
    array = np.ascontiguousarray(array)
    return msgtype("sensor_msgs/msg/Image")(
        header=header(stamp, frame_id),
        height=array.shape[0],
        width=array.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=array.shape[1] * channels * array.dtype.itemsize,
        data=array.reshape(-1).view(np.uint8),
    )


def image_array(msg: Any) -> np.ndarray:
    """The pixels of a sensor_msgs/Image (RGB order for colour)."""
    if msg.encoding not in _DTYPES:
        raise InputError(f"unsupported image encoding {msg.encoding!r}")
    dtype, channels = _DTYPES[msg.encoding]
    itemsize = np.dtype(dtype).itemsize
    expected = msg.height * msg.width * channels * itemsize
    raw = np.asarray(msg.data, dtype=np.uint8)
    if msg.step != msg.width * channels * itemsize or raw.size != expected:
        raise InputError(f"image {msg.width}x{msg.height} {msg.encoding}: {raw.size} bytes, want {expected}")
    arr = raw.view(dtype).reshape(msg.height, msg.width, channels) if channels > 1 else raw.view(dtype).reshape(msg.height, msg.width)
    if msg.is_bigendian and itemsize > 1:
        arr = arr.byteswap()
    if msg.encoding == "bgr8":
        arr = arr[..., ::-1]
    return arr


def camera_info_msg(intr: Intrinsics, stamp: int, frame_id: str) -> Any:
    d = np.asarray(intr.distortion, dtype=np.float64)
    k = intr.matrix.reshape(-1)
    p = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    return msgtype("sensor_msgs/msg/CameraInfo")(
        header=header(stamp, frame_id),
        height=intr.height,
        width=intr.width,
        distortion_model="plumb_bob" if d.size else "",
        d=d,
        k=k.astype(np.float64),
        r=np.eye(3).reshape(-1),
        p=p,
        binning_x=0,
        binning_y=0,
        roi=msgtype("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def intrinsics_from(msg: Any) -> Intrinsics:
    k = np.asarray(msg.k, dtype=np.float64)
    if k.size != 9 or k[0] <= 0 or k[4] <= 0:
        raise InputError("camera_info has no valid K matrix (missing calibration)")
    return Intrinsics(int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                      tuple(float(x) for x in msg.d))


def pose_msg(T: np.ndarray) -> Any:
    t, q = matrix_to_pose(T)
    Point = msgtype("geometry_msgs/msg/Point")
    Quaternion = msgtype("geometry_msgs/msg/Quaternion")
    return msgtype("geometry_msgs/msg/Pose")(
        position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def pose_matrix(msg: Any) -> np.ndarray:
    t, q = _pose_arrays(msg)
    check_pose(t, q)
    return pose_to_matrix(t, q)


def check_pose_msg(msg: Any) -> None:
    """InputError where pose_matrix(msg) would raise one, without building the matrix (a check on
    every message of a log's hot path: scipy's rotation costs more than the check)."""
    check_pose(*_pose_arrays(msg))


def _pose_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    p, o = msg.position, msg.orientation
    return np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w])


def check_pose(t: np.ndarray, q: np.ndarray) -> None:
    """InputError unless the translation is finite and the quaternion finite and not zero."""
    norm = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(t)) and np.isfinite(norm) and norm > 1e-9):
        raise InputError(f"pose: translation {t.tolist()} / quaternion {q.tolist()} is not a rigid transform")


def rgbd_msg(frame: RgbdFrame) -> Any:
    return msgtype("octolog_msgs/msg/RgbdFrame")(
        seq=frame.seq,
        header=header(frame.stamp_ns, frame.frame_id),
        color=image_msg(frame.rgb, frame.stamp_ns, frame.frame_id),
        depth=image_msg(frame.depth, frame.stamp_ns, frame.frame_id),
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id),
    )


def _rgbd_parts(msg: Any) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """Pixels and calibration of an RgbdFrame or Keyframe, or of their Compressed* variants."""
    if hasattr(msg.color, "format"):  # sensor_msgs/CompressedImage: decode transparently
        info = (int(msg.camera_info.width), int(msg.camera_info.height))
        for name, image in (("colour", msg.color), ("depth", msg.depth)):
            size = declared_size(image.data)
            if size is not None and size != info:  # refused before decoding: no allocation past the calibration
                raise InputError(f"image sizes disagree: {name} {size[0]}x{size[1]}, camera_info {info[0]}x{info[1]}")
        rgb, depth = wire_image_array(msg.color), wire_image_array(msg.depth)
        kinds = (msg.color.format, msg.depth.format)
    else:
        rgb, depth = image_array(msg.color), image_array(msg.depth)
        kinds = (msg.color.encoding, msg.depth.encoding)
    intr = intrinsics_from(msg.camera_info)
    if rgb.ndim != 3 or depth.ndim != 2 or depth.dtype != np.uint16:
        raise InputError(f"want rgb8 colour and 16-bit depth, got {kinds[0]} and {kinds[1]}")
    if rgb.shape[:2] != depth.shape or (intr.height, intr.width) != depth.shape:
        raise InputError(
            f"image sizes disagree: colour {rgb.shape[1]}x{rgb.shape[0]}, depth {depth.shape[1]}x{depth.shape[0]}, "
            f"camera_info {intr.width}x{intr.height}"
        )
    if not msg.depth_scale_m > 0:
        raise InputError(f"depth_scale_m must be > 0 metres per unit, got {msg.depth_scale_m}")
    return rgb, depth, intr


def rgbd_from_msg(msg: Any) -> RgbdFrame:
    """The decoded frame; a compressed one keeps its CompressedImage pair in `extra["wire"]`, so a
    keyframe or a log can pass the images on as they came."""
    rgb, depth, intr = _rgbd_parts(msg)
    extra = {"wire": (msg.color, msg.depth)} if hasattr(msg.color, "format") else {}
    return RgbdFrame(int(msg.seq), stamp_ns(msg.header), rgb, depth, float(msg.depth_scale_m), intr,
                     msg.header.frame_id, extra)


def keyframe_msg(kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame) -> Any:
    return msgtype("octolog_msgs/msg/Keyframe")(
        header=header(frame.stamp_ns, "world"),
        id=kf_id,
        frame_seq=frame.seq,
        world_from_camera=pose_msg(world_from_camera),
        color=image_msg(frame.rgb, frame.stamp_ns, frame.frame_id),
        depth=image_msg(frame.depth, frame.stamp_ns, frame.frame_id),
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id),
    )


def keyframe_from_msg(msg: Any) -> tuple[int, np.ndarray, RgbdFrame]:
    rgb, depth, intr = _rgbd_parts(msg)
    frame = RgbdFrame(int(msg.frame_seq), stamp_ns(msg.header), rgb, depth, float(msg.depth_scale_m), intr,
                      msg.color.header.frame_id)
    return int(msg.id), pose_matrix(msg.world_from_camera), frame


def pose_stamped_msg(T: np.ndarray, stamp: int, frame_id: str = "world") -> Any:
    return msgtype("geometry_msgs/msg/PoseStamped")(header=header(stamp, frame_id), pose=pose_msg(T))


def path_msg(stamps_ns: list[int], poses: list[np.ndarray], frame_id: str = "world") -> Any:
    """nav_msgs/Path: one PoseStamped per stamp; the header takes the last stamp."""
    PoseStamped = msgtype("geometry_msgs/msg/PoseStamped")
    return msgtype("nav_msgs/msg/Path")(
        header=header(int(stamps_ns[-1]) if len(stamps_ns) else 0, frame_id),
        poses=[PoseStamped(header=header(int(s), frame_id), pose=pose_msg(T)) for s, T in zip(stamps_ns, poses, strict=True)])


def path_rows(msg: Any) -> tuple[list[int], np.ndarray]:
    """Stamps and (N, 7) rows 'tx ty tz qx qy qz qw' of a nav_msgs/Path (the TUM file's columns)."""
    rows = [(p.pose.position.x, p.pose.position.y, p.pose.position.z, p.pose.orientation.x, p.pose.orientation.y,
             p.pose.orientation.z, p.pose.orientation.w) for p in msg.poses]
    return [stamp_ns(p.header) for p in msg.poses], np.array(rows, dtype=np.float64).reshape(-1, 7)


def config_msg(stage: str, config: dict) -> Any:
    return msgtype("std_msgs/msg/String")(data=json.dumps({"stage": stage, "config": config}, sort_keys=True))


def stream_end_msg(topic: str, count: int, stamp: int = 0) -> Any:
    return msgtype("octolog_msgs/msg/StreamEnd")(header=header(stamp, ""), topic=topic, count=count)


def camera_properties_msg(camera: str, readout_s: float, stamp: int = 0) -> Any:
    return msgtype("octolog_msgs/msg/CameraProperties")(header=header(stamp, ""), camera=camera,
                                                       readout_s=float(readout_s))


def keyframe_poses_msg(poses: dict[int, np.ndarray], stamp: int = 0) -> Any:
    ids = sorted(poses)
    return msgtype("octolog_msgs/msg/KeyframePoses")(
        header=header(stamp, "world"), ids=np.array(ids, dtype=np.uint64),
        world_from_camera=[pose_msg(poses[i]) for i in ids])


def keyframe_poses_from_msg(msg: Any) -> dict[int, np.ndarray]:
    if len(msg.ids) != len(msg.world_from_camera):
        raise InputError(f"keyframe_poses: {len(msg.ids)} ids but {len(msg.world_from_camera)} poses")
    return {int(i): pose_matrix(p) for i, p in zip(msg.ids, msg.world_from_camera, strict=True)}


def vector3_stamped_msg(v: np.ndarray, stamp: int, frame_id: str) -> Any:
    """geometry_msgs/Vector3Stamped."""
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return msgtype("geometry_msgs/msg/Vector3Stamped")(
        header=header(stamp, frame_id), vector=msgtype("geometry_msgs/msg/Vector3")(x=x, y=y, z=z))


def octomap_msg(bt_data: bytes, resolution_m: float, stamp: int, frame_id: str = "map") -> Any:
    """octomap_msgs/Octomap, binary: OctoMap's writeBinaryData bytes (a .bt file without its header)."""
    return msgtype("octomap_msgs/msg/Octomap")(
        header=header(stamp, frame_id), binary=True, id="OcTree", resolution=float(resolution_m),
        data=np.frombuffer(bt_data, dtype=np.int8).copy())


def point_cloud_msg(points: np.ndarray, stamp: int, frame_id: str = "map") -> Any:
    """sensor_msgs/PointCloud2 with float32 x, y, z."""
    PointField = msgtype("sensor_msgs/msg/PointField")
    pts = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 3)
    fields = [PointField(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]  # 7: FLOAT32
    return msgtype("sensor_msgs/msg/PointCloud2")(
        header=header(stamp, frame_id), height=1, width=len(pts), fields=fields, is_bigendian=False,
        point_step=12, row_step=12 * len(pts), data=pts.reshape(-1).view(np.uint8), is_dense=True)


def point_cloud_xyz(msg: Any) -> np.ndarray:
    if msg.point_step != 12 or [f.name for f in msg.fields] != ["x", "y", "z"]:
        raise InputError("point cloud: want packed float32 x, y, z")
    return np.asarray(msg.data, dtype=np.uint8).view("<f4").reshape(-1, 3)


# --- importers (recorder/importers.py, replay/standard.py) --------------------------------------
# One block, appended. The builders for CompressedImage, Imu and /tf_static are the recorder's, below.

# 12-byte ConfigHeader (format enum + two float depth quantization parameters) that
# compressed_depth_image_transport puts before the PNG in "16UC1; compressedDepth png" messages.
_COMPRESSED_DEPTH_HEADER = 12


def decode_compressed_image(msg: Any) -> np.ndarray:
    """The pixels of any CompressedImage we meet: RGB order for colour, uint16 for 16-bit depth.

    Reads plain png/jpeg, image_transport's "rgb8; jpeg compressed bgr8" and "16UC1; png compressed",
    and compressed_depth_image_transport's "16UC1; compressedDepth png" (as librealsense 2.59 records).
    """
    fmt = str(msg.format)
    data = np.asarray(msg.data, dtype=np.uint8)
    if "compresseddepth" in fmt.lower():
        if "rvl" in fmt.lower():
            raise InputError(f"compressed image format {fmt!r}: RVL depth is not supported (want png)")
        data = data[_COMPRESSED_DEPTH_HEADER:]
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"compressed image ({fmt!r}, {data.size} bytes): cannot decode")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return img
# --- end of importers block ---------------------------------------------------------------------


# --- recorder builders ------------------------------------------------------------------------


def compressed_image_msg(data: bytes, fmt: str, stamp: int, frame_id: str) -> Any:
    """sensor_msgs/CompressedImage. `fmt` as image_transport writes it: "rgb8; jpeg compressed bgr8"
    for JPEG colour, "16UC1; png compressed" for lossless 16-bit PNG depth (sensor units kept)."""
    return msgtype("sensor_msgs/msg/CompressedImage")(
        header=header(stamp, frame_id), format=fmt, data=np.frombuffer(data, dtype=np.uint8))


def compressed_image_array(msg: Any) -> np.ndarray:
    """Decode a JPEG (to RGB) or PNG (16-bit depth kept as uint16) CompressedImage."""
    raw = np.asarray(msg.data, dtype=np.uint8)
    img = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"CompressedImage ({msg.format!r}): undecodable data")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


def imu_msg(stamp: int, frame_id: str, *, angular_velocity: tuple[float, float, float] | None = None,
            linear_acceleration: tuple[float, float, float] | None = None) -> Any:
    """sensor_msgs/Imu with what one sensor measured; a missing quantity (and the orientation,
    which a D455 does not estimate) has covariance[0] = -1, as REP 145 asks."""
    Vector3 = msgtype("geometry_msgs/msg/Vector3")
    missing = np.zeros(9, dtype=np.float64)
    missing[0] = -1.0
    gyro = angular_velocity or (0.0, 0.0, 0.0)
    acc = linear_acceleration or (0.0, 0.0, 0.0)
    return msgtype("sensor_msgs/msg/Imu")(
        header=header(stamp, frame_id),
        orientation=msgtype("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=missing.copy(),
        angular_velocity=Vector3(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
        angular_velocity_covariance=np.zeros(9) if angular_velocity is not None else missing.copy(),
        linear_acceleration=Vector3(x=float(acc[0]), y=float(acc[1]), z=float(acc[2])),
        linear_acceleration_covariance=np.zeros(9) if linear_acceleration is not None else missing.copy(),
    )


def tf_msg(transforms: list[tuple[str, str, np.ndarray]], stamp: int) -> Any:
    """tf2_msgs/TFMessage (for /tf or /tf_static) of (parent, child, parent_from_child 4x4) transforms."""
    Vector3 = msgtype("geometry_msgs/msg/Vector3")
    Quaternion = msgtype("geometry_msgs/msg/Quaternion")
    out = []
    for parent, child, T in transforms:
        t, q = matrix_to_pose(np.asarray(T, dtype=np.float64))
        out.append(msgtype("geometry_msgs/msg/TransformStamped")(
            header=header(stamp, parent), child_frame_id=child,
            transform=msgtype("geometry_msgs/msg/Transform")(
                translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))))
    return msgtype("tf2_msgs/msg/TFMessage")(transforms=out)


def tf_transforms(msg: Any) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, parent_from_child 4x4) of a tf2_msgs/TFMessage; a transform that is not
    rigid (not finite, zero quaternion) is left out rather than poisoning a chain."""
    out = []
    for tf in msg.transforms:
        t, q = tf.transform.translation, tf.transform.rotation
        tq = np.array([t.x, t.y, t.z, q.x, q.y, q.z, q.w], dtype=np.float64)
        if np.isfinite(tq).all() and np.any(tq[3:]):
            out.append((str(tf.header.frame_id), str(tf.child_frame_id), pose_to_matrix(tq[:3], tq[3:])))
    return out


# --- wire compression (camera/rgbd/compressed, tracker/keyframe/compressed) ---------------------


@dataclass(frozen=True)
class WireCompression:
    """How a producer compresses images on the wire: colour "jpeg" (lossy, `quality` 1-100) or "png"
    (lossless, zlib `level` 0-9); depth "png" or "zstd" (`depth_zstd`), both lossless in sensor units."""

    colour: str = "jpeg"
    quality: int = 90
    level: int = 1
    depth: str = "png"

    @property
    def colour_format(self) -> str:
        return f"rgb8; {self.colour} compressed bgr8"


DEPTH_PNG_FORMAT = "16UC1; png compressed"
DEPTH_ZSTD_FORMAT = "16UC1; zstd sub compressed"
DEPTH_CODECS = {"png": DEPTH_PNG_FORMAT, "zstd": DEPTH_ZSTD_FORMAT}


SOURCE = "source"  # frames as the source encodes them; keyframes as the frames came


def parse_wire_compression(spec: str) -> WireCompression | None:
    """`"source"`, `""`, `"raw"`: no re-encoding (the caller passes encoded images on as they are,
    or sends raw ones); else `COLOUR[,DEPTH]` with COLOUR `jpeg[:QUALITY]` or `png[:LEVEL]`
    and DEPTH `png` (the default) or `zstd` (`depth_zstd`; depth is never compressed lossily)."""
    if spec in (SOURCE, "", "raw"):
        return None
    colour, _, depth = spec.partition(",")
    depth = depth or "png"
    if depth not in DEPTH_CODECS:
        raise ConfigError(f"wire compression {spec!r}: depth can be png or zstd (lossless), got {depth!r}")
    kind, _, arg = colour.partition(":")
    try:
        value = int(arg) if arg else None
    except ValueError:
        raise ConfigError(f"wire compression {spec!r}: {arg!r} is not an integer") from None
    if kind == "jpeg" and (value is None or 1 <= value <= 100):
        return WireCompression("jpeg", quality=value or 90, depth=depth)
    if kind == "png" and (value is None or 0 <= value <= 9):
        return WireCompression("png", level=1 if value is None else value, depth=depth)
    raise ConfigError(f"wire compression {spec!r}: want raw, or jpeg[:1-100] or png[:0-9] for colour, "
                      f"optionally followed by ,png or ,zstd for depth")


def _encode(image: np.ndarray, ext: str, params: list[int]) -> np.ndarray:
    ok, buf = cv2.imencode(ext, image, params)
    if not ok:
        raise InputError(f"cannot encode a {image.shape} {image.dtype} image as {ext}")
    return buf.reshape(-1)


def depth_png(depth: np.ndarray, level: int = 1) -> np.ndarray:
    """A uint16 depth image as lossless PNG, zlib `level`, with the SUB filter and run-length
    strategy: on 640x480 depth about half the encode time of OpenCV's default PNG settings at the
    same size or smaller (simulated D455 9.5 -> 5.3 ms, 211 -> 205 KB; TUM 7.9 -> 4.2 ms,
    113 -> 101 KB; AMD EPYC, 2026-12-03). Decoding is any PNG decoder's."""
    return _encode(np.ascontiguousarray(depth), ".png", [cv2.IMWRITE_PNG_COMPRESSION, level,
                                                         cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB,
                                                         cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE])


def depth_zstd(depth: np.ndarray, level: int = 1) -> bytes:
    """A uint16 depth image, lossless, as `DEPTH_ZSTD_FORMAT`: "ZSUB", width and height (uint32 LE),
    then one zstd frame (content size set) of the rows' differences (each pixel minus its left
    neighbour, modulo 2^16, the first pixel as it is: PNG's SUB filter on 16-bit samples) as uint16 LE.
    For octolog's own live frames (camera/rgbd/compressed), where PNG's zlib is the costliest step
    of a frame: on 640x480 depth (AMD EPYC, 2026-12-03) encoding takes 2.3 ms against PNG's 5.4 and
    decoding 1.3 against 3.2, at the same size (simulated D455 203 vs 205 KB, TUM 102 vs 104 KB).
    zstd at a fixed level is deterministic for a given library version (pinned)."""
    d = np.ascontiguousarray(depth, dtype="<u2")
    if d.ndim != 2:
        raise InputError(f"depth image must be 2-D, got shape {d.shape}")
    sub = np.empty_like(d)
    sub[:, :1] = d[:, :1]
    np.subtract(d[:, 1:], d[:, :-1], out=sub[:, 1:])
    head = ZSTD_DEPTH_MAGIC + int(d.shape[1]).to_bytes(4, "little") + int(d.shape[0]).to_bytes(4, "little")
    return head + zstandard.ZstdCompressor(level=level).compress(sub.tobytes())


def _depth_from_zstd(raw: np.ndarray, fmt: str) -> np.ndarray:
    """Pixels of a `depth_zstd` image; the frame must decompress to exactly the size its header says."""
    size = declared_size(raw[:ZSTD_DEPTH_HEADER].tobytes())
    if size is None:
        raise InputError(f"CompressedImage ({fmt!r}, {raw.size} bytes): no zstd depth header")
    w, h = size
    body = raw[ZSTD_DEPTH_HEADER:].tobytes()
    try:
        # checked before decompressing: a frame may claim any content size
        if zstandard.frame_content_size(body) != 2 * w * h:
            raise InputError(f"CompressedImage ({fmt!r}, {raw.size} bytes): its zstd frame is not {w}x{h} uint16")
        buf = zstandard.ZstdDecompressor().decompress(body, max_output_size=2 * w * h)
    except zstandard.ZstdError as exc:
        raise InputError(f"CompressedImage ({fmt!r}, {raw.size} bytes): cannot decode ({exc})") from None
    if len(buf) != 2 * w * h:
        raise InputError(f"CompressedImage ({fmt!r}, {raw.size} bytes): {len(buf)} bytes of pixels, want {2 * w * h}")
    return np.cumsum(np.frombuffer(buf, dtype="<u2").reshape(h, w), axis=1, dtype=np.uint16)


def _wire_images(frame: RgbdFrame, wire: WireCompression) -> tuple[Any, Any]:
    """(colour, depth) as CompressedImage messages. OpenCV's encoders are deterministic: the same
    pixels give the same bytes, so lossy JPEG keeps the pipeline's determinism."""
    bgr = np.ascontiguousarray(frame.rgb[..., ::-1])
    if wire.colour == "jpeg":
        colour = _encode(bgr, ".jpg", [cv2.IMWRITE_JPEG_QUALITY, wire.quality])
    else:
        colour = _encode(bgr, ".png", [cv2.IMWRITE_PNG_COMPRESSION, wire.level])
    depth = depth_zstd(frame.depth) if wire.depth == "zstd" else depth_png(frame.depth, wire.level).tobytes()
    return (compressed_image_msg(colour.tobytes(), wire.colour_format, frame.stamp_ns, frame.frame_id),
            compressed_image_msg(depth, DEPTH_CODECS[wire.depth], frame.stamp_ns, frame.frame_id))


def wire_image_array(msg: Any) -> np.ndarray:
    """Pixels of a wire CompressedImage: RGB colour, uint16 depth; bad data is an InputError."""
    raw = np.asarray(msg.data, dtype=np.uint8)
    if msg.format == DEPTH_ZSTD_FORMAT:
        return _depth_from_zstd(raw, msg.format)
    img = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
    if img is None:
        raise InputError(f"CompressedImage ({msg.format!r}, {raw.size} bytes): cannot decode")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


def compressed_rgbd_msg(frame: RgbdFrame, wire: WireCompression) -> Any:
    colour, depth = _wire_images(frame, wire)
    return msgtype("octolog_msgs/msg/CompressedRgbdFrame")(
        seq=frame.seq, header=header(frame.stamp_ns, frame.frame_id), color=colour, depth=depth,
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id))


def encoded_rgbd_msg(frame: EncodedRgbd) -> Any:
    """A CompressedRgbdFrame of images as the source encoded them (no decoding, no re-encoding)."""
    return msgtype("octolog_msgs/msg/CompressedRgbdFrame")(
        seq=frame.seq, header=header(frame.stamp_ns, frame.frame_id),
        color=compressed_image_msg(frame.color, frame.color_format, frame.stamp_ns, frame.frame_id),
        depth=compressed_image_msg(frame.depth, frame.depth_format, frame.stamp_ns, frame.frame_id),
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id))


def encoded_rgbd_from_msg(msg: Any) -> EncodedRgbd:
    """The encoded images and calibration of a CompressedRgbdFrame, still encoded."""
    return EncodedRgbd(int(msg.seq), stamp_ns(msg.header), bytes(msg.color.data), msg.color.format,
                       bytes(msg.depth.data), msg.depth.format, float(msg.depth_scale_m),
                       intrinsics_from(msg.camera_info), msg.header.frame_id)


def forwarded_keyframe_msg(kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame) -> Any:
    """A CompressedKeyframe with the images `frame` arrived with (`extra["wire"]`), not re-encoded."""
    colour, depth = frame.extra["wire"]
    return msgtype("octolog_msgs/msg/CompressedKeyframe")(
        header=header(frame.stamp_ns, "world"), id=kf_id, frame_seq=frame.seq,
        world_from_camera=pose_msg(world_from_camera), color=colour, depth=depth,
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id))


def compressed_keyframe_msg(kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame,
                            wire: WireCompression) -> Any:
    colour, depth = _wire_images(frame, wire)
    return msgtype("octolog_msgs/msg/CompressedKeyframe")(
        header=header(frame.stamp_ns, "world"), id=kf_id, frame_seq=frame.seq,
        world_from_camera=pose_msg(world_from_camera), color=colour, depth=depth,
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id))
