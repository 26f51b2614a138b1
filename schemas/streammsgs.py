"""Messages about a stream rather than of it: a stage's config, a stream's end, the camera's properties."""

from __future__ import annotations

import dataclasses
import json
import math

from octolog.kit import depthmodel
from octolog.kit.depthmodel import DepthModel
from octolog.kit.imu import IMU_NOISE_FIELDS, ImuNoise
from octolog.schemas.codec import header, msgtype
from octolog.schemas.msgtypes import CAMERA_PROPERTIES, STREAM_END, CameraPropertiesMsg, StreamEndMsg, String


def config_msg(stage: str, config: dict[str, object]) -> String:
    return String(data=json.dumps({"stage": stage, "config": config}, sort_keys=True))


def stream_end_msg(topic: str, count: int, stamp: int = 0) -> StreamEndMsg:
    msg: StreamEndMsg = msgtype(STREAM_END)(header=header(stamp, ""), topic=topic, count=count)
    return msg


def camera_properties_msg(camera: str, readout_s: float, stamp: int = 0, depth: DepthModel | None = None,
                          imu_noise: ImuNoise | None = None) -> CameraPropertiesMsg:
    """The camera's properties; `depth` its depth error model, `imu_noise` its IMU's (zeros when unknown)."""
    fields = depth.fields() if depth is not None else dict.fromkeys(depthmodel.FIELDS, 0.0)
    fields.update(zip(IMU_NOISE_FIELDS, dataclasses.astuple(imu_noise) if imu_noise is not None else (0.0,) * 4))
    msg: CameraPropertiesMsg = msgtype(CAMERA_PROPERTIES)(header=header(stamp, ""), camera=camera,
                                                          readout_s=float(readout_s), **fields)
    return msg


def imu_noise_from(msg: CameraPropertiesMsg) -> ImuNoise | None:
    """The IMU noise a CameraProperties carries, None when it has none (zeros)."""
    values = [float(getattr(msg, k)) for k in IMU_NOISE_FIELDS]
    return ImuNoise(*values) if all(v > 0 and math.isfinite(v) for v in values) else None


def depth_model_from(msg: CameraPropertiesMsg) -> DepthModel | None:
    """The depth error model a CameraProperties carries, None when it has none (zeros) or a bad one."""
    try:
        return DepthModel(msg.depth_baseline_m, msg.depth_focal_px, msg.depth_disparity_sigma_px)
    except ValueError:
        return None
