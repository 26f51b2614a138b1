"""Messages about a stream rather than of it: a stage's config, a stream's end, the camera's properties."""

from __future__ import annotations

import json
from typing import Any

from octolog.schemas.codec import header, msgtype
from octolog.schemas.msgtypes import CAMERA_PROPERTIES, STREAM_END, CameraPropertiesMsg, StreamEndMsg, String


def config_msg(stage: str, config: dict[str, Any]) -> String:
    return String(data=json.dumps({"stage": stage, "config": config}, sort_keys=True))


def stream_end_msg(topic: str, count: int, stamp: int = 0) -> StreamEndMsg:
    msg: StreamEndMsg = msgtype(STREAM_END)(header=header(stamp, ""), topic=topic, count=count)
    return msg


def camera_properties_msg(camera: str, readout_s: float, stamp: int = 0) -> CameraPropertiesMsg:
    msg: CameraPropertiesMsg = msgtype(CAMERA_PROPERTIES)(header=header(stamp, ""), camera=camera,
                                                          readout_s=float(readout_s))
    return msg
