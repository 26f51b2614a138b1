"""Topic names and their message types, defined once.

Zenoh keys follow zenoh-bridge-ros2dds: the ROS topic name without its leading `/`, under an
optional namespace (`robot1/camera/rgbd`). Rerun entity paths mirror the same names.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Topic:
    name: str  # ROS name without namespace or leading slash
    msgtype: str

    def key(self, namespace: str = "") -> str:
        """The Zenoh key of this topic under a namespace."""
        ns = namespace.strip("/")
        return f"{ns}/{self.name}" if ns else self.name

    def ros_name(self, namespace: str = "") -> str:
        return "/" + self.key(namespace)


# Camera streams as a recorder writes them (realsense-ros names), one namespace per camera.
COLOR = Topic("camera/color/image_raw", "sensor_msgs/msg/Image")
COLOR_JPEG = Topic("camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage")
COLOR_INFO = Topic("camera/color/camera_info", "sensor_msgs/msg/CameraInfo")
ALIGNED_DEPTH = Topic("camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image")
ALIGNED_DEPTH_PNG = Topic("camera/aligned_depth_to_color/image_raw/compressed", "sensor_msgs/msg/CompressedImage")
ALIGNED_DEPTH_INFO = Topic("camera/aligned_depth_to_color/camera_info", "sensor_msgs/msg/CameraInfo")
DEPTH = Topic("camera/depth/image_rect_raw", "sensor_msgs/msg/Image")
DEPTH_PNG = Topic("camera/depth/image_rect_raw/compressed", "sensor_msgs/msg/CompressedImage")
DEPTH_INFO = Topic("camera/depth/camera_info", "sensor_msgs/msg/CameraInfo")
ACCEL = Topic("camera/accel/sample", "sensor_msgs/msg/Imu")
GYRO = Topic("camera/gyro/sample", "sensor_msgs/msg/Imu")
TF_STATIC = Topic("tf_static", "tf2_msgs/msg/TFMessage")
CAMERA_TOPICS = (COLOR, COLOR_JPEG, COLOR_INFO, ALIGNED_DEPTH, ALIGNED_DEPTH_PNG, ALIGNED_DEPTH_INFO, DEPTH,
                 DEPTH_PNG, DEPTH_INFO, ACCEL, GYRO, TF_STATIC)

# The tracker's input: colour + registered depth + calibration, paired, one message per frame.
RGBD = Topic("camera/rgbd", "octolog_msgs/msg/RgbdFrame")
# The same frames with JPEG/PNG colour and PNG depth, when the producer is configured to compress
# (image_transport's naming); consumers take either, the end message names the one used.
RGBD_COMPRESSED = Topic("camera/rgbd/compressed", "octolog_msgs/msg/CompressedRgbdFrame")
RGBD_END = Topic("camera/rgbd/end", "octolog_msgs/msg/StreamEnd")
# The camera's properties a tracker needs beyond CameraInfo (the rolling-shutter readout), once per stream
CAMERA_PROPERTIES = Topic("camera/rgbd/properties", "octolog_msgs/msg/CameraProperties")
# Up (unit vector, against gravity) in the first frame's optical frame, from a file source's
# accelerometer (octolog.replay.source_gravity), once before the first frame: a mapper that is not told
# `grid_up` builds its `map` frame on it (mapper/mapframe.py)
GRAVITY = Topic("camera/gravity", "geometry_msgs/msg/Vector3Stamped")
# Up (unit vector, against gravity) in `world` as the tracker's IMU estimates it (tracker/inertial.py:
# Inertial.up): once the IMU is trusted, and the session's estimate before the end of the keyframes;
# a mapper whose `map` frame came from an accelerometer rebuilds on it (mapper/mapframe.py)
TRACKER_GRAVITY = Topic("tracker/gravity", "geometry_msgs/msg/Vector3Stamped")
POSE = Topic("tracker/pose", "geometry_msgs/msg/PoseStamped")
TRACKING_STATUS = Topic("tracker/status", "octolog_msgs/msg/TrackingStatus")
# A live tracker's keyframe that went in while the back end was still busy with the previous one
# (JSON in a String: seq, keyframe_id, stamp_ns), so a replay applies its results where it did
BACKEND_DEFERRED = Topic("tracker/backend_deferred", "std_msgs/msg/String")
KEYFRAME = Topic("tracker/keyframe", "octolog_msgs/msg/Keyframe")
KEYFRAME_COMPRESSED = Topic("tracker/keyframe/compressed", "octolog_msgs/msg/CompressedKeyframe")
KEYFRAME_END = Topic("tracker/keyframe/end", "octolog_msgs/msg/StreamEnd")
KEYFRAME_POSES = Topic("tracker/keyframe_poses", "octolog_msgs/msg/KeyframePoses")
MAP_UPDATE = Topic("mapper/update", "octolog_msgs/msg/MapUpdate")
OCTOMAP = Topic("mapper/octomap", "octomap_msgs/msg/Octomap")
OCCUPIED = Topic("mapper/occupied", "sensor_msgs/msg/PointCloud2")
GRID = Topic("mapper/grid", "nav_msgs/msg/OccupancyGrid")
MAP_END = Topic("mapper/end", "octolog_msgs/msg/StreamEnd")
# Several robots without start poses: a robot placed in the map (JSON in a String: which keyframes
# matched, the evidence, world_from_robot), once per robot (mapper/fleet/placement.py)
MAP_MERGE = Topic("mapper/merge", "std_msgs/msg/String")
# A sharded map's placement authority: every call the placing shard makes on its map, in order (one
# JSON object per sample; mapper/fleet/journal.py), for the shards that follow it (`mapper.follow`)
MAP_PLACED = Topic("mapper/placed", "std_msgs/msg/String")


def route_topic(shard: int, robot: int, compressed: bool) -> Topic:
    """A robot's keyframes routed by the placing shard to shard `shard` (the ones that reach its tiles),
    as the robot sent them: `mapper/route/<shard>/<robot index>`, `.../compressed` for compressed ones."""
    name = f"mapper/route/{shard}/{robot}"
    return Topic(f"{name}/compressed", KEYFRAME_COMPRESSED.msgtype) if compressed else Topic(name, KEYFRAME.msgtype)

# The frames (docs/formats.md "Frames"): the tracker's camera in `world` on every frame; the
# mapper's `map` -> `world` once (REP 105's map frame: z up)
TF = Topic("tf", "tf2_msgs/msg/TFMessage")

# The tracker's trajectory at the end: every tracked frame at its final pose (what its trajectory
# file holds), so a machine that only logs has it too. Announced on tracker/keyframe/end.
TRAJECTORY = Topic("tracker/trajectory", "nav_msgs/msg/Path")
# Each stage's resolved configuration (JSON in a String), once when it starts: a log written on
# another machine holds the settings a replay of it needs.
CONFIGS = {stage: Topic(f"{stage}/config", "std_msgs/msg/String") for stage in ("replay", "tracker", "mapper")}

ALL = (RGBD, RGBD_END, POSE, TRACKING_STATUS, KEYFRAME, KEYFRAME_END, KEYFRAME_POSES, MAP_UPDATE, OCTOMAP,
       OCCUPIED, GRID, MAP_END, RGBD_COMPRESSED, KEYFRAME_COMPRESSED, CAMERA_PROPERTIES, TF, TF_STATIC, TRAJECTORY,
       MAP_MERGE, GRAVITY, BACKEND_DEFERRED, GYRO, ACCEL, TRACKER_GRAVITY, MAP_PLACED,
       *CONFIGS.values())
# The camera frames: what stays on a robot when the log runs elsewhere (`octolog log --no-frames`)
FRAMES = (RGBD, RGBD_COMPRESSED)
# The mapper's queryable: a late joiner `get`s the current map (octomap_msgs/Octomap, binary).
MAP_QUERY = Topic("mapper/map", "octomap_msgs/msg/Octomap")
# Ask the mapper to write its files now; the reply (JSON in a String) names them.
MAP_SAVE = Topic("mapper/save", "std_msgs/msg/String")
BY_NAME = {t.name: t for t in ALL + CAMERA_TOPICS}

# Liveliness tokens: a stage declares `<ns>/_octolog/stage/<name>` once it is subscribed and ready.
STAGE_TOKEN = "_octolog/stage"
# what the tracker says once it has taken every camera frame (kit/bus `say_taken`): a live camera
# lingering for it may close then, while the tracker finishes
FRAMES_TAKEN = "frames"


def stage_token(stage: str, namespace: str = "") -> str:
    ns = namespace.strip("/")
    return f"{ns}/{STAGE_TOKEN}/{stage}" if ns else f"{STAGE_TOKEN}/{stage}"
