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


RGBD = Topic("camera/rgbd", "octolog_msgs/msg/RgbdFrame")
RGBD_END = Topic("camera/rgbd/end", "octolog_msgs/msg/StreamEnd")
POSE = Topic("tracker/pose", "geometry_msgs/msg/PoseStamped")
TRACKING_STATUS = Topic("tracker/status", "octolog_msgs/msg/TrackingStatus")
KEYFRAME = Topic("tracker/keyframe", "octolog_msgs/msg/Keyframe")
KEYFRAME_END = Topic("tracker/keyframe/end", "octolog_msgs/msg/StreamEnd")
KEYFRAME_POSES = Topic("tracker/keyframe_poses", "octolog_msgs/msg/KeyframePoses")
MAP_UPDATE = Topic("mapper/update", "octolog_msgs/msg/MapUpdate")
OCTOMAP = Topic("mapper/octomap", "octomap_msgs/msg/Octomap")
OCCUPIED = Topic("mapper/occupied", "sensor_msgs/msg/PointCloud2")
GRID = Topic("mapper/grid", "nav_msgs/msg/OccupancyGrid")
MAP_END = Topic("mapper/end", "octolog_msgs/msg/StreamEnd")

ALL = (RGBD, RGBD_END, POSE, TRACKING_STATUS, KEYFRAME, KEYFRAME_END, KEYFRAME_POSES, MAP_UPDATE, OCTOMAP,
       OCCUPIED, GRID, MAP_END)
# The mapper's queryable: a late joiner `get`s the current map (octomap_msgs/Octomap, binary).
MAP_QUERY = Topic("mapper/map", "octomap_msgs/msg/Octomap")
# Ask the mapper to write its files now; the reply (JSON in a String) names them.
MAP_SAVE = Topic("mapper/save", "std_msgs/msg/String")
BY_NAME = {t.name: t for t in ALL}

# Liveliness tokens: a stage declares `<ns>/_octolog/stage/<name>` once it is subscribed and ready.
STAGE_TOKEN = "_octolog/stage"


def stage_token(stage: str, namespace: str = "") -> str:
    ns = namespace.strip("/")
    return f"{ns}/{STAGE_TOKEN}/{stage}" if ns else f"{STAGE_TOKEN}/{stage}"
