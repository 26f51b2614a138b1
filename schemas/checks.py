"""Cheap structural checks of a decoded wire message, before a stage spends anything on it.

CDR decoding (codec.decode) proves a payload has the type's shape; these checks prove its sizes are
sane and agree with each other, without decoding an image: a raw image's byte count against its
header, a compressed image's signature and the size its own header declares (a PNG or JPEG can claim
a 10^9-pixel image in 30 bytes, and decoding it would allocate gigabytes), the calibration's size
against both. A message that passes can still be refused later (an image that does not decode); it
cannot make a stage allocate more than its declared size.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from octolog.kit.errors import InputError
from octolog.schemas.codec import IMAGE_ENCODINGS, pose_matrix

MAX_SIDE = 16384  # pixels: no camera a stage takes has a wider or taller image
_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_FRAMES = ("octolog_msgs/msg/RgbdFrame", "octolog_msgs/msg/CompressedRgbdFrame",
           "octolog_msgs/msg/Keyframe", "octolog_msgs/msg/CompressedKeyframe")


def check(msg: Any, typename: str) -> None:
    """Raise InputError naming what is wrong if `msg` (of `typename`) is not a sane message."""
    if typename in _FRAMES:
        _check_frame(msg)
        if hasattr(msg, "world_from_camera"):  # a keyframe
            pose_matrix(msg.world_from_camera)
    elif typename == "octolog_msgs/msg/KeyframePoses":
        if len(msg.ids) != len(msg.world_from_camera):
            raise InputError(f"keyframe_poses: {len(msg.ids)} ids but {len(msg.world_from_camera)} poses")
        for pose in msg.world_from_camera:
            pose_matrix(pose)
    elif typename == "geometry_msgs/msg/PoseStamped":
        pose_matrix(msg.pose)
    elif typename == "octolog_msgs/msg/TrackingStatus":
        if not math.isfinite(msg.processing_ms):
            raise InputError(f"tracking status: processing_ms {msg.processing_ms}")


def _check_frame(msg: Any) -> None:
    info = msg.camera_info
    w, h = int(info.width), int(info.height)
    if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE):
        raise InputError(f"camera_info: image size {w}x{h} (want 1..{MAX_SIDE} a side)")
    if not (math.isfinite(msg.depth_scale_m) and msg.depth_scale_m > 0):
        raise InputError(f"depth_scale_m must be > 0 metres per unit, got {msg.depth_scale_m}")
    for name, image in (("colour", msg.color), ("depth", msg.depth)):
        size = _compressed_size(image) if hasattr(image, "format") else _raw_size(image)
        if size != (w, h):
            raise InputError(f"{name} image is {size[0]}x{size[1]}, camera_info says {w}x{h}")


def _raw_size(image: Any) -> tuple[int, int]:
    w, h, enc = int(image.width), int(image.height), image.encoding
    if enc not in IMAGE_ENCODINGS:
        raise InputError(f"unsupported image encoding {enc!r}")
    dtype, channels = IMAGE_ENCODINGS[enc]
    row = w * channels * np.dtype(dtype).itemsize
    want = row * h
    if image.step != row or len(image.data) != want:
        raise InputError(f"image {w}x{h} {enc}: {len(image.data)} bytes, want {want}")
    return w, h


def _compressed_size(image: Any) -> tuple[int, int]:
    """The width and height a PNG or JPEG's own header declares (read from the header only)."""
    data = bytes(image.data[:65536])  # the header, never the whole image
    if data.startswith(_PNG) and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return w, h
    if data.startswith(b"\xff\xd8"):
        size = _jpeg_size(data)
        if size is not None:
            return size
    raise InputError(f"CompressedImage ({image.format!r}, {len(image.data)} bytes): not a PNG or JPEG image")


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """Width and height from a JPEG's start-of-frame segment, walking the segments before it."""
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
            i += 2
            continue
        length = struct.unpack(">H", data[i + 2:i + 4])[0]
        if length < 2:
            return None
        if marker in _JPEG_SOF:
            if i + 9 > len(data):
                return None
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        i += 2 + length
    return None
