"""ROS 1/ROS 2 bag messages into the recorder's layout: the plan every bag importer follows, stamps,
pixels, and field-by-field copies (ROS 1 and ROS 2 spellings alike) into the ROS 2 types written."""

from __future__ import annotations

from typing import Any

import numpy as np

from octolog.kit.errors import InputError
from octolog.recorder.import_output import DEFAULT_DEPTH_SCALE_M, ImportSink
from octolog.schemas import codec, imagecodec, sensormsgs
from octolog.schemas.topics import ALIGNED_DEPTH, CAMERA_TOPICS, COLOR, DEPTH

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMU = "sensor_msgs/msg/Imu"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
BAG_TYPES = (IMAGE, COMPRESSED, CAMERA_INFO, IMU, TF_MESSAGE)

LAYOUT_BY_NAME = {t.name: t for t in CAMERA_TOPICS}
# Image topics whose pixels the layout fixes (rgb8 colour, 16UC1 depth).
COLOR_TOPICS = {COLOR.name}
DEPTH_TOPICS = {ALIGNED_DEPTH.name, DEPTH.name}


class BagPlan:
    """How one kind of bag is imported: what it writes, and what it says about depth, calibration
    and the source (`import_bag` puts these into the metadata records)."""

    kind = ""
    notes: list[str]

    def write(self, sink: ImportSink) -> None: ...

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


def header_stamp_ns(hdr: Any) -> int:
    return int(hdr.stamp.sec) * 1_000_000_000 + int(hdr.stamp.nanosec)


def ros_field(msg: Any, name: str) -> Any:
    """A field by its ROS 2 name, also on ROS 1 messages (CameraInfo's D, K, R, P)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def pixels(msg: Any, topic: str) -> np.ndarray:
    """Pixels of a decoded Image or CompressedImage (RGB order for colour)."""
    try:
        if msg.__msgtype__ == COMPRESSED:
            return imagecodec.decode_compressed_image(msg)
        if msg.encoding in ("rgba8", "bgra8"):
            raw = np.asarray(msg.data, dtype=np.uint8)
            if msg.step != msg.width * 4 or raw.size != msg.height * msg.step:
                raise InputError(f"image {msg.width}x{msg.height} {msg.encoding}: {raw.size} bytes")
            arr = raw.reshape(msg.height, msg.width, 4)[..., :3]
            return arr[..., ::-1] if msg.encoding == "bgra8" else arr
        return sensormsgs.image_array(msg)
    except InputError as exc:
        raise InputError(f"{topic}: {exc}") from None


def layout_image(msg: Any, source_topic: str, target: str, stamp: int, frame_id: str) -> Any:
    """An Image for a layout topic: rgb8 colour or little-endian 16UC1 depth."""
    arr = pixels(msg, source_topic)
    if target in COLOR_TOPICS and not (arr.ndim == 3 and arr.dtype == np.uint8):
        raise InputError(f"{source_topic}: {encoding_of(msg)} is not 8-bit colour; /{target} wants rgb8")
    if target in DEPTH_TOPICS and not (arr.ndim == 2 and arr.dtype == np.uint16):
        raise InputError(f"{source_topic}: depth {encoding_of(msg)} is not 16-bit integer units; /{target} wants "
                         "16UC1 (float metres would lose the sensor's units)")
    return sensormsgs.image_msg(np.ascontiguousarray(arr), stamp, frame_id)


def encoding_of(msg: Any) -> str:
    return str(msg.format) if msg.__msgtype__ == COMPRESSED else str(msg.encoding)


def copy_image(msg: Any, stamp: int) -> Any:
    return codec.msgtype(IMAGE)(header=codec.header(stamp, msg.header.frame_id), height=msg.height, width=msg.width,
                                encoding=msg.encoding, is_bigendian=msg.is_bigendian, step=msg.step,
                                data=np.asarray(msg.data, dtype=np.uint8))


def copy_compressed(msg: Any, stamp: int) -> Any:
    return codec.msgtype(COMPRESSED)(header=codec.header(stamp, msg.header.frame_id), format=msg.format,
                                     data=np.asarray(msg.data, dtype=np.uint8))


def copy_camera_info(msg: Any, stamp: int) -> Any:
    roi = msg.roi
    return codec.msgtype(CAMERA_INFO)(
        header=codec.header(stamp, msg.header.frame_id), height=msg.height, width=msg.width,
        distortion_model=msg.distortion_model, d=np.asarray(ros_field(msg, "d"), dtype=np.float64),
        k=np.asarray(ros_field(msg, "k"), dtype=np.float64), r=np.asarray(ros_field(msg, "r"), dtype=np.float64),
        p=np.asarray(ros_field(msg, "p"), dtype=np.float64), binning_x=msg.binning_x, binning_y=msg.binning_y,
        roi=codec.msgtype("sensor_msgs/msg/RegionOfInterest")(x_offset=roi.x_offset, y_offset=roi.y_offset,
                                                              height=roi.height, width=roi.width,
                                                              do_rectify=roi.do_rectify))


def copy_imu(msg: Any, stamp: int, frame_id: str | None = None) -> Any:
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


def copy_tf(msg: Any) -> Any:
    V, Q = codec.msgtype("geometry_msgs/msg/Vector3"), codec.msgtype("geometry_msgs/msg/Quaternion")
    out = []
    for ts in msg.transforms:
        t, q = ts.transform.translation, ts.transform.rotation
        out.append(codec.msgtype("geometry_msgs/msg/TransformStamped")(
            header=codec.header(header_stamp_ns(ts.header), ts.header.frame_id), child_frame_id=ts.child_frame_id,
            transform=codec.msgtype("geometry_msgs/msg/Transform")(translation=V(x=t.x, y=t.y, z=t.z),
                                                                   rotation=Q(x=q.x, y=q.y, z=q.z, w=q.w))))
    return codec.msgtype(TF_MESSAGE)(transforms=out)
