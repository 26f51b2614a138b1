"""Cheap structural checks of a decoded wire message, before a stage spends anything on it.

CDR decoding (codec.decode) proves a payload has the type's shape; these checks prove it is a
message a stage can afford to look at, without decoding an image: a raw image's byte count against
its header, a compressed image's signature and the size its own header declares (imageheaders), the
sides and pixel counts of images and calibration within what any RGB-D camera has, rigid poses.

What is left to the stage on purpose: whether a frame agrees with its camera (image sizes against the
calibration, depth type, a depth scale > 0). Such a frame is still a frame of its producer's stream:
the tracker consumes it and reports it LOST (a lockstep replay waits for that status), where a
sample dropped here was never a message at all. rgbdmsgs compares a compressed image's declared size
with the calibration before decoding it, so no frame makes a stage allocate past its calibration.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from octolog.kit.errors import InputError
from octolog.schemas.codec import decode
from octolog.schemas.imageheaders import declared_size
from octolog.schemas.msgtypes import FrameMsg, Image, Pose
from octolog.schemas.sensormsgs import IMAGE_ENCODINGS

MAX_SIDE = 8192  # pixels: no RGB-D camera a stage takes has a wider or taller image
MAX_PIXELS = 1 << 25  # 33.5 Mpx: 100 MB of RGB, the most one frame may make a stage allocate
_FRAMES = ("octolog_msgs/msg/RgbdFrame", "octolog_msgs/msg/CompressedRgbdFrame",
           "octolog_msgs/msg/Keyframe", "octolog_msgs/msg/CompressedKeyframe")


def checked(data: bytes | memoryview, typename: str) -> Any:
    """The message `data` holds, decoded and checked; InputError naming the problem."""
    msg = decode(data, typename)
    check(msg, typename)
    return msg


def check(msg: Any, typename: str) -> None:
    """Raise InputError naming what is wrong if `msg` (of `typename`) is not a sane message."""
    if typename in _FRAMES:
        _check_frame(msg)
        if hasattr(msg, "world_from_camera"):  # a keyframe
            check_pose_msg(msg.world_from_camera)
    elif typename == "octolog_msgs/msg/KeyframePoses":
        if len(msg.ids) != len(msg.world_from_camera):
            raise InputError(f"keyframe_poses: {len(msg.ids)} ids but {len(msg.world_from_camera)} poses")
        for pose in msg.world_from_camera:
            check_pose_msg(pose)
    elif typename == "geometry_msgs/msg/PoseStamped":
        check_pose_msg(msg.pose)
    elif typename == "octolog_msgs/msg/CameraProperties":
        if not (math.isfinite(msg.readout_s) and 0.0 <= msg.readout_s <= 0.1):
            raise InputError(f"camera properties: readout_s {msg.readout_s} (want 0..0.1 s)")
    elif typename == "octolog_msgs/msg/TrackingStatus":
        if not math.isfinite(msg.processing_ms):
            raise InputError(f"tracking status: processing_ms {msg.processing_ms}")


def _check_frame(msg: FrameMsg) -> None:
    info = msg.camera_info
    _check_size("camera_info", int(info.width), int(info.height), allow_empty=True)
    for name, image in (("colour", msg.color), ("depth", msg.depth)):
        if hasattr(image, "format"):
            size = declared_size(image.data)
            if size is None:
                raise InputError(f"{name} CompressedImage ({image.format!r}, {len(image.data)} bytes): "
                                 f"not a PNG, JPEG or zstd depth image")
        else:
            size = _raw_size(image)
        _check_size(f"{name} image", *size)


def _check_size(what: str, w: int, h: int, *, allow_empty: bool = False) -> None:
    """Sides and pixel count a stage may allocate for (a calibration may be empty: the stage says so)."""
    if allow_empty and w == h == 0:
        return
    if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE and w * h <= MAX_PIXELS):
        raise InputError(f"{what}: {w}x{h} pixels (want 1..{MAX_SIDE} a side, at most {MAX_PIXELS} pixels)")


def _raw_size(image: Image) -> tuple[int, int]:
    w, h, enc = int(image.width), int(image.height), image.encoding
    if enc not in IMAGE_ENCODINGS:
        raise InputError(f"unsupported image encoding {enc!r}")
    dtype, channels = IMAGE_ENCODINGS[enc]
    row = w * channels * np.dtype(dtype).itemsize
    want = row * h
    if image.step != row or len(image.data) != want:
        raise InputError(f"image {w}x{h} {enc}: {len(image.data)} bytes, want {want}")
    return w, h




def check_pose(t: np.ndarray, q: np.ndarray) -> None:
    """InputError unless the translation is finite and the quaternion finite and not zero."""
    norm = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(t)) and np.isfinite(norm) and norm > 1e-9):
        raise InputError(f"pose: translation {t.tolist()} / quaternion {q.tolist()} is not a rigid transform")


def check_pose_msg(msg: Pose) -> None:
    """InputError where posemsgs.pose_matrix(msg) would raise one, without building the matrix (a
    check on every message of a log's hot path: scipy's rotation costs more than the check)."""
    check_pose(*pose_arrays(msg))


def pose_arrays(msg: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Translation and quaternion (x, y, z, w) of a geometry_msgs/Pose."""
    p, o = msg.position, msg.orientation
    return np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w])
