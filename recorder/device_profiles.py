"""Choosing and describing a RealSense device's streams: the profiles a `CaptureProfile` asks for
(a missing one raises naming what is supported), the sensor options to set, and the resolved
device info and calibration that go into every recording.

Shared by both backends (a real camera and the software D455), so they resolve profiles, options
and calibration the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyrealsense2 as rs

from octolog.kit.errors import RecorderError
from octolog.kit.geometry import Intrinsics
from octolog.recorder.capture import MOTION_STREAMS, CaptureProfile, DeviceDescription, DeviceOptions


def _f32(x: float) -> float:
    """A float32 from librealsense as the decimal it stands for (0.001, not 0.0010000000474974513)."""
    return float(str(np.float32(x)))


def _fps_list(rates: list[int]) -> str:
    return "/".join(str(r) for r in sorted(set(rates)))


def _supported_video(sensors: list[Any], stream: Any, fmt: Any) -> dict[tuple[int, int], list[int]]:
    out: dict[tuple[int, int], list[int]] = {}
    for s in sensors:
        for p in s.get_stream_profiles():
            if p.stream_type() == stream and p.format() == fmt and p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                out.setdefault((v.width(), v.height()), []).append(p.fps())
    return out


def _find_video(sensors: list[Any], stream: Any, fmt: Any, want: tuple[int, int, int], label: str,
                device: str) -> tuple[Any, Any]:
    for s in sensors:
        for p in s.get_stream_profiles():
            if p.stream_type() == stream and p.format() == fmt and p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                if (v.width(), v.height(), p.fps()) == want:
                    return s, v
    supported = _supported_video(sensors, stream, fmt)
    listing = ", ".join(f"{w}x{h}@{_fps_list(r)}" for (w, h), r in sorted(supported.items(), reverse=True))
    w, h, fps = want
    fmt_name = str(fmt).split(".")[-1]
    if not supported:
        raise RecorderError(f"{device} has no {label} stream in {fmt_name}")
    raise RecorderError(f"{label} {w}x{h}@{fps} is not supported by {device}; supported ({fmt_name}): {listing}")


def _find_motion(sensors: list[Any], stream: Any, fps: int, label: str, device: str) -> tuple[Any, Any] | None:
    cands = []
    for s in sensors:
        for p in s.get_stream_profiles():
            if p.stream_type() == stream and p.is_motion_stream_profile():
                cands.append((s, p))
    if not cands:
        return None
    if fps == 0:  # the device's default rate, else its lowest
        for s, p in cands:
            if p.is_default():
                return s, p.as_motion_stream_profile()
        s, p = min(cands, key=lambda sp: sp[1].fps())
        return s, p.as_motion_stream_profile()
    for s, p in cands:
        if p.fps() == fps:
            return s, p.as_motion_stream_profile()
    raise RecorderError(f"{label} at {fps} Hz is not supported by {device}; supported: "
                        f"{_fps_list([p.fps() for _, p in cands])} Hz")


def _matrix(ext: Any) -> np.ndarray:
    """librealsense extrinsics (column-major rotation) as a 4x4 `to_from_from` matrix."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(ext.rotation, dtype=np.float64).reshape(3, 3).T
    T[:3, 3] = ext.translation
    return T


def _intrinsics(vp: Any) -> tuple[Intrinsics, str]:
    i = vp.get_intrinsics()
    model = str(i.model).split(".")[-1]
    coeffs = tuple(float(c) for c in i.coeffs)
    return Intrinsics(i.width, i.height, float(i.fx), float(i.fy), float(i.ppx), float(i.ppy),
                      coeffs if any(coeffs) or model != "none" else ()), model


@dataclass
class Resolved:
    """Sensor profiles chosen for a CaptureProfile, per stream, with the sensors that own them."""

    profiles: dict[str, tuple[Any, Any]] = field(default_factory=dict)  # stream -> (sensor, profile)

    def by_sensor(self) -> list[tuple[Any, list[Any]]]:
        out: list[tuple[Any, list[Any]]] = []
        for sensor, profile in self.profiles.values():
            for s, ps in out:
                if s == sensor:
                    ps.append(profile)
                    break
            else:
                out.append((sensor, [profile]))
        return out


def resolve(device: Any, profile: CaptureProfile) -> Resolved:
    """Find the requested profiles among the device's; a missing one raises naming what is supported."""
    name = device.get_info(rs.camera_info.name) if device.supports(rs.camera_info.name) else "the device"
    sensors = list(device.query_sensors())
    res = Resolved()
    res.profiles["color"] = _find_video(sensors, rs.stream.color, rs.format.rgb8, profile.color, "colour", name)
    res.profiles["depth"] = _find_video(sensors, rs.stream.depth, rs.format.z16, profile.depth, "depth", name)
    if profile.imu:
        for label, stream, fps in (("gyro", rs.stream.gyro, profile.gyro_fps),
                                   ("accel", rs.stream.accel, profile.accel_fps)):
            found = _find_motion(sensors, stream, fps, label, name)
            if found is None:
                raise RecorderError(f"{name} has no {label} stream (an IMU-less model?); record with --no-imu")
            res.profiles[label] = found
    return res


_OPTION_NAMES = {"depth_units_m": "depth_units", "emitter": "emitter_enabled", "visual_preset": "visual_preset",
                 "color_auto_exposure": "enable_auto_exposure", "depth_auto_exposure": "enable_auto_exposure",
                 "color_exposure": "exposure", "depth_exposure": "exposure"}
_EMITTER = {"off": 0.0, "on": 1.0, "auto": 2.0}


def apply_options(res: Resolved, opts: DeviceOptions) -> dict[str, float]:
    """Set the requested options on the depth and colour sensors; the values in force afterwards."""
    depth_sensor = res.profiles["depth"][0]
    color_sensor = res.profiles["color"][0]
    wanted: list[tuple[str, Any, Any, float]] = []  # key, sensor, option, value
    if opts.depth_units_m is not None:
        wanted.append(("depth_units_m", depth_sensor, rs.option.depth_units, opts.depth_units_m))
    if opts.visual_preset is not None:
        presets = rs.rs400_visual_preset.__members__  # the name was checked by RecorderConfig.validate
        wanted.append(("visual_preset", depth_sensor, rs.option.visual_preset,
                       float(int(presets[opts.visual_preset]))))
    if opts.emitter is not None:
        wanted.append(("emitter", depth_sensor, rs.option.emitter_enabled, _EMITTER[opts.emitter]))
    if opts.depth_auto_exposure is not None:
        wanted.append(("depth_auto_exposure", depth_sensor, rs.option.enable_auto_exposure,
                       float(opts.depth_auto_exposure)))
    if opts.depth_exposure is not None:
        wanted.append(("depth_exposure", depth_sensor, rs.option.exposure, opts.depth_exposure))
    if opts.color_auto_exposure is not None:
        wanted.append(("color_auto_exposure", color_sensor, rs.option.enable_auto_exposure,
                       float(opts.color_auto_exposure)))
    if opts.color_exposure is not None:
        wanted.append(("color_exposure", color_sensor, rs.option.exposure, opts.color_exposure))
    for key, sensor, option, value in wanted:
        if not sensor.supports(option):
            raise RecorderError(f"option {key}: not supported by the {sensor.get_info(rs.camera_info.name)}")
        if abs(float(sensor.get_option(option)) - value) <= 1e-6 * max(1.0, abs(value)):
            continue  # already so (float options refuse to be set to their own value on some sensors)
        r = sensor.get_option_range(option)
        if not r.min <= value <= r.max:
            raise RecorderError(f"option {key}={value:g}: outside the device's range {r.min:g}..{r.max:g}")
        try:
            sensor.set_option(option, value)
        except RuntimeError as exc:
            raise RecorderError(f"option {key}={value:g}: the device refused it ({exc})") from None
    now: dict[str, float] = {}
    for key, sensor in (("depth_units_m", depth_sensor), ("visual_preset", depth_sensor),
                        ("emitter", depth_sensor), ("depth_auto_exposure", depth_sensor),
                        ("depth_exposure", depth_sensor), ("color_auto_exposure", color_sensor),
                        ("color_exposure", color_sensor)):
        option = getattr(rs.option, _OPTION_NAMES[key])
        if sensor.supports(option):
            try:
                now[key] = _f32(sensor.get_option(option))
            except RuntimeError:
                pass
    return now


def describe(device: Any, res: Resolved, backend: str, options: dict[str, float]) -> DeviceDescription:
    """Device info and calibration of the resolved profiles."""
    def info(key: Any) -> str:
        return device.get_info(key) if device.supports(key) else ""

    _, cp = res.profiles["color"]
    dsensor, dp = res.profiles["depth"]
    color, cmodel = _intrinsics(cp)
    depth, dmodel = _intrinsics(dp)
    try:
        scale = dsensor.as_depth_sensor().get_depth_scale()
    except RuntimeError:
        scale = dsensor.get_option(rs.option.depth_units)
    scale = _f32(scale)
    desc = DeviceDescription(
        name=info(rs.camera_info.name), serial=info(rs.camera_info.serial_number),
        firmware=info(rs.camera_info.firmware_version), backend=backend,
        product_line=info(rs.camera_info.product_line), usb_type=info(rs.camera_info.usb_type_descriptor),
        depth_scale_m=scale, color=color, depth=depth, color_fps=cp.fps(), depth_fps=dp.fps(),
        color_from_depth=_matrix(dp.get_extrinsics_to(cp)), options=options,
        distortion_models={"color": cmodel, "depth": dmodel})
    for label in MOTION_STREAMS:
        if label not in res.profiles:
            continue
        _, mp = res.profiles[label]
        setattr(desc, f"{label}_fps", mp.fps())
        try:
            setattr(desc, f"depth_from_{label}", _matrix(mp.get_extrinsics_to(dp)))
        except RuntimeError:
            pass
        try:
            mi = mp.get_motion_intrinsics()
            desc.motion_intrinsics[label] = {"data": np.asarray(mi.data, dtype=float).tolist(),
                                             "noise_variances": [float(x) for x in mi.noise_variances],
                                             "bias_variances": [float(x) for x in mi.bias_variances]}
        except RuntimeError:
            pass  # not calibrated on this unit
    return desc
