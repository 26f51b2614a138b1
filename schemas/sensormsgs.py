"""sensor_msgs on the wire: raw and compressed images, camera calibration, IMU samples."""

from __future__ import annotations

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics
from octolog.schemas.codec import header
from octolog.schemas.msgtypes import CameraInfo, CompressedImage, Image, Imu, Quaternion, RegionOfInterest, Vector3

_ENCODINGS = {("uint8", 3): "rgb8", ("uint16", 1): "16UC1", ("uint8", 1): "mono8", ("float32", 1): "32FC1"}
_DTYPES = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "16UC1": (np.uint16, 1), "mono16": (np.uint16, 1),
           "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "32FC1": (np.float32, 1)}
IMAGE_ENCODINGS = _DTYPES  # sensor_msgs/Image encodings taken: numpy dtype, channels


def image_msg(array: np.ndarray, stamp: int, frame_id: str) -> Image:
    channels = 1 if array.ndim == 2 else array.shape[2]
    encoding = _ENCODINGS[(array.dtype.name, channels)]
    array = np.ascontiguousarray(array)
    return Image(
        header=header(stamp, frame_id),
        height=array.shape[0],
        width=array.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=array.shape[1] * channels * array.dtype.itemsize,
        data=array.reshape(-1).view(np.uint8),
    )


def image_array(msg: Image) -> np.ndarray:
    """The pixels of a sensor_msgs/Image (RGB order for colour)."""
    if msg.encoding not in _DTYPES:
        raise InputError(f"unsupported image encoding {msg.encoding!r}")
    dtype, channels = _DTYPES[msg.encoding]
    itemsize = np.dtype(dtype).itemsize
    expected = msg.height * msg.width * channels * itemsize
    raw = np.asarray(msg.data, dtype=np.uint8)
    if msg.step != msg.width * channels * itemsize or raw.size != expected:
        raise InputError(f"image {msg.width}x{msg.height} {msg.encoding}: {raw.size} bytes, want {expected}")
    arr = raw.view(dtype).reshape(msg.height, msg.width, channels) if channels > 1 else raw.view(dtype).reshape(msg.height, msg.width)
    if msg.is_bigendian and itemsize > 1:
        arr = arr.byteswap()
    if msg.encoding == "bgr8":
        arr = arr[..., ::-1]
    return arr


def camera_info_msg(intr: Intrinsics, stamp: int, frame_id: str) -> CameraInfo:
    d = np.asarray(intr.distortion, dtype=np.float64)
    k = intr.matrix.reshape(-1)
    p = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    return CameraInfo(
        header=header(stamp, frame_id),
        height=intr.height,
        width=intr.width,
        distortion_model="plumb_bob" if d.size else "",
        d=d,
        k=k.astype(np.float64),
        r=np.eye(3).reshape(-1),
        p=p,
        binning_x=0,
        binning_y=0,
        roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def intrinsics_from(msg: CameraInfo) -> Intrinsics:
    k = np.asarray(msg.k, dtype=np.float64)
    if k.size != 9 or k[0] <= 0 or k[4] <= 0:
        raise InputError("camera_info has no valid K matrix (missing calibration)")
    return Intrinsics(int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                      tuple(float(x) for x in msg.d))


def compressed_image_msg(data: bytes, fmt: str, stamp: int, frame_id: str) -> CompressedImage:
    """sensor_msgs/CompressedImage. `fmt` as image_transport writes it: "rgb8; jpeg compressed bgr8"
    for JPEG colour, "16UC1; png compressed" for lossless 16-bit PNG depth (sensor units kept)."""
    return CompressedImage(header=header(stamp, frame_id), format=fmt, data=np.frombuffer(data, dtype=np.uint8))


def imu_msg(stamp: int, frame_id: str, *, angular_velocity: tuple[float, float, float] | None = None,
            linear_acceleration: tuple[float, float, float] | None = None) -> Imu:
    """sensor_msgs/Imu with what one sensor measured; a missing quantity (and the orientation,
    which a D455 does not estimate) has covariance[0] = -1, as REP 145 asks."""
    missing = np.zeros(9, dtype=np.float64)
    missing[0] = -1.0
    gyro = angular_velocity or (0.0, 0.0, 0.0)
    acc = linear_acceleration or (0.0, 0.0, 0.0)
    return Imu(
        header=header(stamp, frame_id),
        orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=missing.copy(),
        angular_velocity=Vector3(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
        angular_velocity_covariance=np.zeros(9) if angular_velocity is not None else missing.copy(),
        linear_acceleration=Vector3(x=float(acc[0]), y=float(acc[1]), z=float(acc[2])),
        linear_acceleration_covariance=np.zeros(9) if linear_acceleration is not None else missing.copy(),
    )
