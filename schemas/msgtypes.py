"""The wire contract's message classes, for type hints and for building stock messages.

Stock ROS 2 types are the type store's classes of Jazzy's types (schemas/typestore.py), the very
classes `codec.typestore()` decodes into; type checkers see rosbags' static Jazzy classes of the same
fields. octolog's own types (`msg/*.msg`) are registered at run time, so rosbags generates their
classes then; the Protocols here spell out the same fields, in the same order and with the same
types (tests/schemas/test_schemas.py checks them against the type store).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np

from octolog.schemas.typestore import STORE

# Type checkers see rosbags' static Jazzy classes; at run time the names are the type store's own
# classes of the same fields (schemas/stocktypes.py), which is what decode() returns.
if TYPE_CHECKING:
    from rosbags.typesys.stores.ros2_jazzy import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_jazzy import diagnostic_msgs__msg__DiagnosticArray as DiagnosticArray
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Point as Point
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Pose as Pose
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__PoseStamped as PoseStamped
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Quaternion as Quaternion
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Transform as Transform
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__TransformStamped as TransformStamped
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Vector3 as Vector3
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Vector3Stamped as Vector3Stamped
    from rosbags.typesys.stores.ros2_jazzy import nav_msgs__msg__MapMetaData as MapMetaData
    from rosbags.typesys.stores.ros2_jazzy import nav_msgs__msg__OccupancyGrid as OccupancyGrid
    from rosbags.typesys.stores.ros2_jazzy import nav_msgs__msg__Path as Path
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__CameraInfo as CameraInfo
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__CompressedImage as CompressedImage
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__Image as Image
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__Imu as Imu
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__PointCloud2 as PointCloud2
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__PointField as PointField
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__RegionOfInterest as RegionOfInterest
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String
    from rosbags.typesys.stores.ros2_jazzy import tf2_msgs__msg__TFMessage as TFMessage
else:
    _CLASSES = STORE.types
    Time = _CLASSES["builtin_interfaces/msg/Time"]
    DiagnosticArray = _CLASSES["diagnostic_msgs/msg/DiagnosticArray"]
    Point = _CLASSES["geometry_msgs/msg/Point"]
    Pose = _CLASSES["geometry_msgs/msg/Pose"]
    PoseStamped = _CLASSES["geometry_msgs/msg/PoseStamped"]
    Quaternion = _CLASSES["geometry_msgs/msg/Quaternion"]
    Transform = _CLASSES["geometry_msgs/msg/Transform"]
    TransformStamped = _CLASSES["geometry_msgs/msg/TransformStamped"]
    Vector3 = _CLASSES["geometry_msgs/msg/Vector3"]
    Vector3Stamped = _CLASSES["geometry_msgs/msg/Vector3Stamped"]
    MapMetaData = _CLASSES["nav_msgs/msg/MapMetaData"]
    OccupancyGrid = _CLASSES["nav_msgs/msg/OccupancyGrid"]
    Path = _CLASSES["nav_msgs/msg/Path"]
    CameraInfo = _CLASSES["sensor_msgs/msg/CameraInfo"]
    CompressedImage = _CLASSES["sensor_msgs/msg/CompressedImage"]
    Image = _CLASSES["sensor_msgs/msg/Image"]
    Imu = _CLASSES["sensor_msgs/msg/Imu"]
    PointCloud2 = _CLASSES["sensor_msgs/msg/PointCloud2"]
    PointField = _CLASSES["sensor_msgs/msg/PointField"]
    RegionOfInterest = _CLASSES["sensor_msgs/msg/RegionOfInterest"]
    Header = _CLASSES["std_msgs/msg/Header"]
    String = _CLASSES["std_msgs/msg/String"]
    TFMessage = _CLASSES["tf2_msgs/msg/TFMessage"]

STOCK = (Time, Header, String, Point, Quaternion, Pose, PoseStamped, Vector3, Vector3Stamped, Transform,
         TransformStamped, TFMessage, Path, Image, CompressedImage, CameraInfo, RegionOfInterest, Imu,
         PointField, PointCloud2, MapMetaData, OccupancyGrid, DiagnosticArray)

U8Array = np.ndarray[tuple[int, ...], np.dtype[np.uint8]]
I8Array = np.ndarray[tuple[int, ...], np.dtype[np.int8]]
U64Array = np.ndarray[tuple[int, ...], np.dtype[np.uint64]]

RGBD_FRAME = "octolog_msgs/msg/RgbdFrame"
COMPRESSED_RGBD_FRAME = "octolog_msgs/msg/CompressedRgbdFrame"
KEYFRAME = "octolog_msgs/msg/Keyframe"
COMPRESSED_KEYFRAME = "octolog_msgs/msg/CompressedKeyframe"
KEYFRAME_POSES = "octolog_msgs/msg/KeyframePoses"
CAMERA_PROPERTIES = "octolog_msgs/msg/CameraProperties"
STREAM_END = "octolog_msgs/msg/StreamEnd"
TRACKING_STATUS = "octolog_msgs/msg/TrackingStatus"
MAP_UPDATE = "octolog_msgs/msg/MapUpdate"
OCTOMAP = "octomap_msgs/msg/Octomap"


class RgbdFrameMsg(Protocol):
    """octolog_msgs/msg/RgbdFrame."""

    seq: int
    header: Header
    color: Image
    depth: Image
    depth_scale_m: float
    camera_info: CameraInfo


class CompressedRgbdFrameMsg(Protocol):
    """octolog_msgs/msg/CompressedRgbdFrame."""

    seq: int
    header: Header
    color: CompressedImage
    depth: CompressedImage
    depth_scale_m: float
    camera_info: CameraInfo


class KeyframeMsg(Protocol):
    """octolog_msgs/msg/Keyframe."""

    header: Header
    id: int
    frame_seq: int
    world_from_camera: Pose
    color: Image
    depth: Image
    depth_scale_m: float
    camera_info: CameraInfo
    depth_inverse_offset: float


class CompressedKeyframeMsg(Protocol):
    """octolog_msgs/msg/CompressedKeyframe."""

    header: Header
    id: int
    frame_seq: int
    world_from_camera: Pose
    color: CompressedImage
    depth: CompressedImage
    depth_scale_m: float
    camera_info: CameraInfo
    depth_inverse_offset: float


class KeyframePosesMsg(Protocol):
    """octolog_msgs/msg/KeyframePoses."""

    header: Header
    ids: U64Array
    world_from_camera: list[Pose]
    depth_inverse_offset: float


class CameraPropertiesMsg(Protocol):
    """octolog_msgs/msg/CameraProperties."""

    header: Header
    camera: str
    readout_s: float
    depth_baseline_m: float
    depth_focal_px: float
    depth_disparity_sigma_px: float
    imu_gyro_noise: float
    imu_accel_noise: float
    imu_gyro_walk: float
    imu_accel_walk: float


class StreamEndMsg(Protocol):
    """octolog_msgs/msg/StreamEnd."""

    header: Header
    topic: str
    count: int


class TrackingStatusMsg(Protocol):
    """octolog_msgs/msg/TrackingStatus."""

    INIT: ClassVar[int]
    OK: ClassVar[int]
    LOST: ClassVar[int]
    SKIPPED: ClassVar[int]
    INERTIAL: ClassVar[int]
    header: Header
    seq: int
    state: int
    is_keyframe: bool
    keyframe_id: int
    n_matches: int
    n_inliers: int
    processing_ms: float
    map_moved_m: float
    relocalised: bool
    imu_gyro_count: int
    imu_accel_count: int


class MapUpdateMsg(Protocol):
    """octolog_msgs/msg/MapUpdate."""

    header: Header
    keyframe_id: int
    n_points: int
    n_occupied: int
    n_free: int
    processing_ms: float


class OctomapMsg(Protocol):
    """octomap_msgs/msg/Octomap (vendored)."""

    header: Header
    binary: bool
    id: str
    resolution: float
    data: I8Array


# typename -> the Protocol its generated class satisfies
OWN: dict[str, type] = {
    RGBD_FRAME: RgbdFrameMsg, COMPRESSED_RGBD_FRAME: CompressedRgbdFrameMsg, KEYFRAME: KeyframeMsg,
    COMPRESSED_KEYFRAME: CompressedKeyframeMsg, KEYFRAME_POSES: KeyframePosesMsg,
    CAMERA_PROPERTIES: CameraPropertiesMsg, STREAM_END: StreamEndMsg, TRACKING_STATUS: TrackingStatusMsg,
    MAP_UPDATE: MapUpdateMsg, OCTOMAP: OctomapMsg,
}
# The frame-carrying messages, raw or compressed (one image pair and its calibration each)
FrameMsg = RgbdFrameMsg | CompressedRgbdFrameMsg | KeyframeMsg | CompressedKeyframeMsg
