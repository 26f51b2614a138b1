"""A Capture as the messages the recorder writes: pure functions of the capture, the device
description, the TF frame names and the encoding settings (no state, safe on any thread)."""

from __future__ import annotations

import cv2
import numpy as np

from octolog.kit.geometry import Intrinsics
from octolog.recorder.capture import Capture, DeviceDescription
from octolog.recorder.recording_types import JPEG_FORMAT, PNG_FORMAT, Encoded, Encoding
from octolog.schemas import codec, imagecodec, posemsgs, sensormsgs
from octolog.schemas import topics as T
from octolog.schemas.topics import Topic


def encode_capture(cap: Capture, device: DeviceDescription, frames: dict[str, str], enc: Encoding) -> list[Encoded]:
    """CDR messages of one Capture, in the order they are written: colour and its calibration,
    aligned depth, raw depth (each with its calibration), then the IMU samples. cv2 releases the
    GIL, so captures encode in parallel on a pool."""
    out: list[Encoded] = []
    if cap.color is not None:
        c = cap.color
        if enc.color_codec == "jpeg":
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(c.array, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, enc.jpeg_quality])
            msg = sensormsgs.compressed_image_msg(buf.tobytes(), JPEG_FORMAT, c.stamp_ns, frames["color"])
            out.append(Encoded(T.COLOR_JPEG, codec.encode(msg, T.COLOR_JPEG.msgtype), c.stamp_ns))
        else:
            msg = sensormsgs.image_msg(c.array, c.stamp_ns, frames["color"])
            out.append(Encoded(T.COLOR, codec.encode(msg, T.COLOR.msgtype), c.stamp_ns))
        out.append(camera_info(T.COLOR_INFO, device.color, c.stamp_ns, frames["color"]))
    for v, raw, png, info, intr, frame in (
            (cap.aligned_depth, T.ALIGNED_DEPTH, T.ALIGNED_DEPTH_PNG, T.ALIGNED_DEPTH_INFO, device.color,
             frames["color"]),
            (cap.depth, T.DEPTH, T.DEPTH_PNG, T.DEPTH_INFO, device.depth, frames["depth"])):
        if v is None:
            continue
        if enc.depth_codec == "png":
            msg = sensormsgs.compressed_image_msg(imagecodec.depth_png(v.array, enc.png_level).tobytes(), PNG_FORMAT,
                                                  v.stamp_ns, frame)
            out.append(Encoded(png, codec.encode(msg, png.msgtype), v.stamp_ns))
        else:
            msg = sensormsgs.image_msg(v.array, v.stamp_ns, frame)
            out.append(Encoded(raw, codec.encode(msg, raw.msgtype), v.stamp_ns))
        out.append(camera_info(info, intr, v.stamp_ns, frame))
    for m in cap.motion:
        topic = T.GYRO if m.stream == "gyro" else T.ACCEL
        kw = {"angular_velocity" if m.stream == "gyro" else "linear_acceleration": m.xyz}
        msg = sensormsgs.imu_msg(m.stamp_ns, frames[m.stream], **kw)
        out.append(Encoded(topic, codec.encode(msg, topic.msgtype), m.stamp_ns))
    return out


def camera_info(topic: Topic, intr: Intrinsics | None, stamp_ns: int, frame: str) -> Encoded:
    """A CameraInfo message of the calibration `intr` for one frame."""
    assert intr is not None
    return Encoded(topic, codec.encode(sensormsgs.camera_info_msg(intr, stamp_ns, frame), topic.msgtype), stamp_ns)


def tf_static(transforms: list[tuple[str, str, np.ndarray]], stamp_ns: int) -> Encoded:
    """The camera's static TF tree (recording_types.camera_transforms) as one message."""
    return Encoded(T.TF_STATIC, codec.encode(posemsgs.tf_msg(transforms, stamp_ns), T.TF_STATIC.msgtype), stamp_ns)
