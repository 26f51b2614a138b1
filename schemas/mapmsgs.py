"""The map on the wire: an OctoMap's binary tree and a point cloud of its occupied cells."""

from __future__ import annotations

import numpy as np

from octolog.kit.errors import InputError
from octolog.schemas.codec import header, msgtype
from octolog.schemas.msgtypes import OCTOMAP, OctomapMsg, PointCloud2, PointField


def octomap_msg(bt_data: bytes, resolution_m: float, stamp: int, frame_id: str = "map") -> OctomapMsg:
    """octomap_msgs/Octomap, binary: OctoMap's writeBinaryData bytes (a .bt file without its header)."""
    msg: OctomapMsg = msgtype(OCTOMAP)(
        header=header(stamp, frame_id), binary=True, id="OcTree", resolution=float(resolution_m),
        data=np.frombuffer(bt_data, dtype=np.int8).copy())
    return msg


def point_cloud_msg(points: np.ndarray, stamp: int, frame_id: str = "map") -> PointCloud2:
    """sensor_msgs/PointCloud2 with float32 x, y, z."""
    pts = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 3)
    fields = [PointField(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]  # 7: FLOAT32
    return PointCloud2(
        header=header(stamp, frame_id), height=1, width=len(pts), fields=fields, is_bigendian=False,
        point_step=12, row_step=12 * len(pts), data=pts.reshape(-1).view(np.uint8), is_dense=True)


def point_cloud_xyz(msg: PointCloud2) -> np.ndarray:
    if msg.point_step != 12 or [f.name for f in msg.fields] != ["x", "y", "z"]:
        raise InputError("point cloud: want packed float32 x, y, z")
    return np.asarray(msg.data, dtype=np.uint8).view("<f4").reshape(-1, 3)
