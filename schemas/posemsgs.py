"""Poses on the wire: Pose, PoseStamped, Path, KeyframePoses, TF, Vector3Stamped, and back to matrices."""

from __future__ import annotations

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import matrix_to_pose, pose_to_matrix
from octolog.schemas.checks import check_pose, pose_arrays
from octolog.schemas.codec import header, msgtype, stamp_ns
from octolog.schemas.msgtypes import (
    KEYFRAME_POSES,
    KeyframePosesMsg,
    Path,
    Point,
    Pose,
    PoseStamped,
    Quaternion,
    TFMessage,
    Transform,
    TransformStamped,
    Vector3,
    Vector3Stamped,
)


def pose_msg(T: np.ndarray) -> Pose:
    t, q = matrix_to_pose(T)
    return Pose(
        position=Point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )


def pose_matrix(msg: Pose) -> np.ndarray:
    t, q = pose_arrays(msg)
    check_pose(t, q)
    return pose_to_matrix(t, q)


def pose_stamped_msg(T: np.ndarray, stamp: int, frame_id: str = "world") -> PoseStamped:
    return PoseStamped(header=header(stamp, frame_id), pose=pose_msg(T))


def path_msg(stamps_ns: list[int], poses: list[np.ndarray], frame_id: str = "world") -> Path:
    """nav_msgs/Path: one PoseStamped per stamp; the header takes the last stamp."""
    return Path(
        header=header(int(stamps_ns[-1]) if len(stamps_ns) else 0, frame_id),
        poses=[PoseStamped(header=header(int(s), frame_id), pose=pose_msg(T)) for s, T in zip(stamps_ns, poses, strict=True)])


def path_rows(msg: Path) -> tuple[list[int], np.ndarray]:
    """Stamps and (N, 7) rows 'tx ty tz qx qy qz qw' of a nav_msgs/Path (the TUM file's columns)."""
    rows = [(p.pose.position.x, p.pose.position.y, p.pose.position.z, p.pose.orientation.x, p.pose.orientation.y,
             p.pose.orientation.z, p.pose.orientation.w) for p in msg.poses]
    return [stamp_ns(p.header) for p in msg.poses], np.array(rows, dtype=np.float64).reshape(-1, 7)


def keyframe_poses_msg(poses: dict[int, np.ndarray], stamp: int = 0, depth_inverse_offset: float = 0.0
                       ) -> KeyframePosesMsg:
    ids = sorted(poses)
    msg: KeyframePosesMsg = msgtype(KEYFRAME_POSES)(
        header=header(stamp, "world"), ids=np.array(ids, dtype=np.uint64),
        world_from_camera=[pose_msg(poses[i]) for i in ids], depth_inverse_offset=float(depth_inverse_offset))
    return msg


def keyframe_poses_from_msg(msg: KeyframePosesMsg) -> dict[int, np.ndarray]:
    if len(msg.ids) != len(msg.world_from_camera):
        raise InputError(f"keyframe_poses: {len(msg.ids)} ids but {len(msg.world_from_camera)} poses")
    return {int(i): pose_matrix(p) for i, p in zip(msg.ids, msg.world_from_camera, strict=True)}


def vector3_stamped_msg(v: np.ndarray, stamp: int, frame_id: str) -> Vector3Stamped:
    """geometry_msgs/Vector3Stamped."""
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return Vector3Stamped(header=header(stamp, frame_id), vector=Vector3(x=x, y=y, z=z))


def tf_msg(transforms: list[tuple[str, str, np.ndarray]], stamp: int) -> TFMessage:
    """tf2_msgs/TFMessage (for /tf or /tf_static) of (parent, child, parent_from_child 4x4) transforms."""
    out = []
    for parent, child, T in transforms:
        t, q = matrix_to_pose(np.asarray(T, dtype=np.float64))
        out.append(TransformStamped(
            header=header(stamp, parent), child_frame_id=child,
            transform=Transform(
                translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))))
    return TFMessage(transforms=out)


def tf_transforms(msg: TFMessage) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, parent_from_child 4x4) of a tf2_msgs/TFMessage; a transform that is not
    rigid (not finite, zero quaternion) is left out rather than poisoning a chain."""
    out = []
    for tf in msg.transforms:
        t, q = tf.transform.translation, tf.transform.rotation
        tq = np.array([t.x, t.y, t.z, q.x, q.y, q.z, q.w], dtype=np.float64)
        if np.isfinite(tq).all() and np.any(tq[3:]):
            out.append((str(tf.header.frame_id), str(tf.child_frame_id), pose_to_matrix(tq[:3], tq[3:])))
    return out
