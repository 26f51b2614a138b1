"""RGB-D frames and keyframes on the wire, raw or compressed, and back to `RgbdFrame`s.

A compressed image's declared size is compared with the calibration before it is decoded, so no
frame makes a stage allocate past its calibration.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import EncodedRgbd, Intrinsics, RgbdFrame
from octolog.schemas.codec import header, msgtype, stamp_ns
from octolog.schemas.imagecodec import wire_image_array, wire_images
from octolog.schemas.imageheaders import declared_size
from octolog.schemas.msgtypes import (
    COMPRESSED_KEYFRAME,
    COMPRESSED_RGBD_FRAME,
    KEYFRAME,
    RGBD_FRAME,
    CompressedImage,
    CompressedKeyframeMsg,
    CompressedRgbdFrameMsg,
    FrameMsg,
    KeyframeMsg,
    RgbdFrameMsg,
)
from octolog.schemas.posemsgs import pose_matrix, pose_msg
from octolog.schemas.sensormsgs import camera_info_msg, compressed_image_msg, image_array, image_msg, intrinsics_from
from octolog.schemas.wirecompression import WireCompression


def rgbd_msg(frame: RgbdFrame) -> RgbdFrameMsg:
    msg: RgbdFrameMsg = msgtype(RGBD_FRAME)(
        seq=frame.seq,
        header=header(frame.stamp_ns, frame.frame_id),
        color=image_msg(frame.rgb, frame.stamp_ns, frame.frame_id),
        depth=image_msg(frame.depth, frame.stamp_ns, frame.frame_id),
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id),
    )
    return msg


def _decoded_images(msg: FrameMsg) -> tuple[np.ndarray, np.ndarray, tuple[str, str]]:
    """Colour and depth pixels of a frame message, and the encodings or formats they came in."""
    if hasattr(msg.color, "format"):  # sensor_msgs/CompressedImage: decode transparently
        info = (int(msg.camera_info.width), int(msg.camera_info.height))
        for name, image in (("colour", msg.color), ("depth", msg.depth)):
            size = declared_size(image.data)
            if size is not None and size != info:  # refused before decoding: no allocation past the calibration
                raise InputError(f"image sizes disagree: {name} {size[0]}x{size[1]}, camera_info {info[0]}x{info[1]}")
        return wire_image_array(msg.color), wire_image_array(msg.depth), (msg.color.format, msg.depth.format)
    return image_array(msg.color), image_array(msg.depth), (msg.color.encoding, msg.depth.encoding)


def _rgbd_parts(msg: FrameMsg) -> tuple[np.ndarray, np.ndarray, Intrinsics]:
    """Pixels and calibration of an RgbdFrame or Keyframe, or of their Compressed* variants."""
    rgb, depth, kinds = _decoded_images(msg)
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


def rgbd_from_msg(msg: RgbdFrameMsg | CompressedRgbdFrameMsg) -> RgbdFrame:
    """The decoded frame; a compressed one keeps its CompressedImage pair in `extra["wire"]`, so a
    keyframe or a log can pass the images on as they came."""
    rgb, depth, intr = _rgbd_parts(msg)
    extra = {"wire": (msg.color, msg.depth)} if hasattr(msg.color, "format") else {}
    return RgbdFrame(int(msg.seq), stamp_ns(msg.header), rgb, depth, float(msg.depth_scale_m), intr,
                     msg.header.frame_id, extra)


def keyframe_msg(kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame) -> KeyframeMsg:
    msg: KeyframeMsg = msgtype(KEYFRAME)(
        header=header(frame.stamp_ns, "world"),
        id=kf_id,
        frame_seq=frame.seq,
        world_from_camera=pose_msg(world_from_camera),
        color=image_msg(frame.rgb, frame.stamp_ns, frame.frame_id),
        depth=image_msg(frame.depth, frame.stamp_ns, frame.frame_id),
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id),
        depth_inverse_offset=float(frame.depth_inverse_offset),
    )
    return msg


def keyframe_from_msg(msg: KeyframeMsg | CompressedKeyframeMsg) -> tuple[int, np.ndarray, RgbdFrame]:
    rgb, depth, intr = _rgbd_parts(msg)
    frame = RgbdFrame(int(msg.frame_seq), stamp_ns(msg.header), rgb, depth, float(msg.depth_scale_m), intr,
                      msg.color.header.frame_id, depth_inverse_offset=float(msg.depth_inverse_offset))
    return int(msg.id), pose_matrix(msg.world_from_camera), frame


def compressed_rgbd_msg(frame: RgbdFrame, wire: WireCompression) -> CompressedRgbdFrameMsg:
    colour, depth = wire_images(frame, wire)
    msg: CompressedRgbdFrameMsg = msgtype(COMPRESSED_RGBD_FRAME)(
        seq=frame.seq, header=header(frame.stamp_ns, frame.frame_id), color=colour, depth=depth,
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id))
    return msg


def encoded_rgbd_msg(frame: EncodedRgbd) -> CompressedRgbdFrameMsg:
    """A CompressedRgbdFrame of images as the source encoded them (no decoding, no re-encoding)."""
    msg: CompressedRgbdFrameMsg = msgtype(COMPRESSED_RGBD_FRAME)(
        seq=frame.seq, header=header(frame.stamp_ns, frame.frame_id),
        color=compressed_image_msg(frame.color, frame.color_format, frame.stamp_ns, frame.frame_id),
        depth=compressed_image_msg(frame.depth, frame.depth_format, frame.stamp_ns, frame.frame_id),
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id))
    return msg


def encoded_rgbd_from_msg(msg: CompressedRgbdFrameMsg) -> EncodedRgbd:
    """The encoded images and calibration of a CompressedRgbdFrame, still encoded."""
    return EncodedRgbd(int(msg.seq), stamp_ns(msg.header), bytes(msg.color.data), msg.color.format,
                       bytes(msg.depth.data), msg.depth.format, float(msg.depth_scale_m),
                       intrinsics_from(msg.camera_info), msg.header.frame_id)


def forwarded_keyframe_msg(kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame) -> CompressedKeyframeMsg:
    """A CompressedKeyframe with the images `frame` arrived with (`extra["wire"]`), not re-encoded."""
    colour, depth = frame.extra["wire"]
    return _compressed_keyframe(kf_id, world_from_camera, frame, colour, depth)


def compressed_keyframe_msg(kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame,
                            wire: WireCompression) -> CompressedKeyframeMsg:
    colour, depth = wire_images(frame, wire)
    return _compressed_keyframe(kf_id, world_from_camera, frame, colour, depth)


def _compressed_keyframe(kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame, colour: CompressedImage,
                         depth: CompressedImage) -> CompressedKeyframeMsg:
    msg: CompressedKeyframeMsg = msgtype(COMPRESSED_KEYFRAME)(
        header=header(frame.stamp_ns, "world"), id=kf_id, frame_seq=frame.seq,
        world_from_camera=pose_msg(world_from_camera), color=colour, depth=depth,
        depth_scale_m=float(frame.depth_scale_m),
        camera_info=camera_info_msg(frame.intrinsics, frame.stamp_ns, frame.frame_id),
        depth_inverse_offset=float(frame.depth_inverse_offset))
    return msg
