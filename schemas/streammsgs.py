"""Messages about a stream rather than of it: a stage's config, a stream's end, the camera's properties."""

from __future__ import annotations

import json
from typing import Any

from octolog.kit import depthmodel
from octolog.kit.depthmodel import DepthModel
from octolog.schemas.codec import header, msgtype
from octolog.schemas.msgtypes import CAMERA_PROPERTIES, STREAM_END, CameraPropertiesMsg, StreamEndMsg, String


def config_msg(stage: str, config: dict[str, Any]) -> String:
    return String(data=json.dumps({"stage": stage, "config": config}, sort_keys=True))


def stream_end_msg(topic: str, count: int, stamp: int = 0) -> StreamEndMsg:
    msg: StreamEndMsg = msgtype(STREAM_END)(header=header(stamp, ""), topic=topic, count=count)
    return msg


def camera_properties_msg(camera: str, readout_s: float, stamp: int = 0, depth: DepthModel | None = None
                          ) -> CameraPropertiesMsg:
    """The camera's properties; `depth` its depth error model (zeros when unknown)."""
    fields = depth.fields() if depth is not None else dict.fromkeys(depthmodel.FIELDS, 0.0)
    msg: CameraPropertiesMsg = msgtype(CAMERA_PROPERTIES)(header=header(stamp, ""), camera=camera,
                                                          readout_s=float(readout_s), **fields)
    return msg


def depth_model_from(msg: CameraPropertiesMsg) -> DepthModel | None:
    """The depth error model a CameraProperties carries, None when it has none (zeros) or a bad one."""
    try:
        return DepthModel(msg.depth_baseline_m, msg.depth_focal_px, msg.depth_disparity_sigma_px)
    except ValueError:
        return None
