"""TUM RGB-D folder -> MCAP in the recorder's layout: colour, registered depth, accelerometer
samples, the sequence's calibration and its ground truth as metadata.

The folder is read with replay.tum's reader, so an imported sequence and one replayed directly
pair and calibrate their frames the same way.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from octolog.kit import depthmodel
from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics
from octolog.kit.tum import TUM_DEPTH_SCALE_M, open_tum, read_list, read_png, read_rows, readout_for, seconds_to_ns
from octolog.recorder.import_output import ACCEL_FRAME, COLOR_FRAME, ImportResult, intrinsics_fields, open_output
from octolog.schemas import posemsgs, sensormsgs
from octolog.schemas.topics import ACCEL, ALIGNED_DEPTH, ALIGNED_DEPTH_INFO, COLOR, COLOR_INFO, TF_STATIC

# The Kinect's accelerometer axes in the colour camera's optical frame (x left, y up, z forward:
# measured against fr1/xyz's ground truth, octolog.replay.source_gravity): colour_from_accel, a half turn
# about the optical axis
COLOR_FROM_KINECT_ACCEL = np.diag([-1.0, -1.0, 1.0, 1.0])


def import_tum(folder: Path, output: Path, *, overwrite: bool = False, compression: str = "zstd",
               intrinsics: Intrinsics | None = None, camera: str = "",
               progress: Callable[[int], None] | None = None) -> ImportResult:
    """TUM RGB-D folder -> MCAP: every listed colour and depth image (registered depth, 1/5000 m),
    accelerometer.txt as Imu (the Kinect's own axes, placed by a /tf_static), groundtruth.txt as
    metadata; stamps exact from the decimal seconds."""
    folder = Path(folder)
    seq = open_tum(folder, intrinsics, camera=camera)  # validates the folder; the camera's intrinsics unless given
    intr = seq.intrinsics
    rgb = sorted(read_list(folder / "rgb.txt"), key=lambda r: r[0])
    depth = sorted(read_list(folder / "depth.txt"), key=lambda r: r[0])
    accel = _read_accelerometer(folder / "accelerometer.txt", seconds_to_ns)
    # Colour before depth before IMU at equal stamps; stable, so list order is kept.
    events = sorted([(t, 0, i) for i, (t, _) in enumerate(rgb)] + [(t, 1, i) for i, (t, _) in enumerate(depth)]
                    + [(t, 2, i) for i, (t, _) in enumerate(accel)], key=lambda e: (e[0], e[1]))
    result = ImportResult(folder, Path(output), "tum", depth_scale_m=TUM_DEPTH_SCALE_M, depth_registered=True)
    with open_output(output, overwrite=overwrite, compression=compression, progress=progress) as sink:
        if accel:  # where the samples' axes lie, as realsense-ros says it for its IMU
            first = events[0][0]
            sink.put(TF_STATIC.name, TF_STATIC.msgtype,
                     posemsgs.tf_msg([(COLOR_FRAME, ACCEL_FRAME, COLOR_FROM_KINECT_ACCEL)], first), first)
        for stamp, what, i in events:
            if what == 0:
                _put_colour(sink, folder / rgb[i][1], stamp, intr)
            elif what == 1:
                _put_depth(sink, folder / depth[i][1], stamp, intr)
            else:
                sink.put(ACCEL.name, ACCEL.msgtype,
                         sensormsgs.imu_msg(stamp, ACCEL_FRAME, linear_acceleration=accel[i][1]), stamp)
        sink.metadata("calibration", {
            "depth_scale_m": repr(TUM_DEPTH_SCALE_M),
            "depth_scale_source": "TUM RGB-D: 5000 depth units per metre",
            "depth_registered_to_color": "true",
            # the colour camera's rolling-shutter readout time (s), for the tracker; 0 = not known
            "color_readout_s": repr(readout_for(seq.camera)),
            # the depth camera's error model (kit/depthmodel.py): the freiburg cameras are Kinect v1 / Xtion
            **{k: repr(v) for k, v in depthmodel.KINECT.fields().items()},
            **intrinsics_fields("color", intr),
            "intrinsics_source": ("given on import" if intrinsics is not None
                                  else f"TUM RGB-D ROS default calibration of {seq.camera}"),
        })
        sink.metadata("source", {"kind": "tum", "path": str(folder.resolve()), "importer": "octolog import",
                                 "rgb_images": len(rgb), "depth_images": len(depth),
                                 "accelerometer_samples": len(accel), "pairs_within_20ms": len(seq)})
        if seq.groundtruth is not None:
            sink.metadata("groundtruth", {"tum": seq.groundtruth.read_text()})
        result.counts = dict(sink.counts)
    if not accel:
        result.notes.append("no accelerometer.txt: no IMU written")
    if seq.groundtruth is None:
        result.notes.append("no groundtruth.txt: no ground truth written")
    return result


def _put_colour(sink: Any, path: Path, stamp: int, intr: Intrinsics) -> None:
    img = read_png(path, cv2.IMREAD_COLOR)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"{path}: not a 3-channel colour image")
    _check_size(path, img, intr)
    sink.put(COLOR.name, COLOR.msgtype, sensormsgs.image_msg(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), stamp,
                                                        COLOR_FRAME), stamp)
    sink.put(COLOR_INFO.name, COLOR_INFO.msgtype, sensormsgs.camera_info_msg(intr, stamp, COLOR_FRAME), stamp)


def _put_depth(sink: Any, path: Path, stamp: int, intr: Intrinsics) -> None:
    img = read_png(path, cv2.IMREAD_ANYDEPTH)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise InputError(f"{path}: depth must be a 16-bit single-channel PNG")
    _check_size(path, img, intr)
    # Registered depth: realsense-ros stamps it in the colour optical frame.
    sink.put(ALIGNED_DEPTH.name, ALIGNED_DEPTH.msgtype, sensormsgs.image_msg(img, stamp, COLOR_FRAME), stamp)
    sink.put(ALIGNED_DEPTH_INFO.name, ALIGNED_DEPTH_INFO.msgtype,
             sensormsgs.camera_info_msg(intr, stamp, COLOR_FRAME), stamp)


def _read_accelerometer(path: Path, to_ns: Callable[[str], int]) -> list[tuple[int, tuple[float, float, float]]]:
    if not path.is_file():
        return []

    def parse(parts: list[str]) -> tuple[int, tuple[float, float, float]]:
        if len(parts) != 4:
            raise ValueError
        return to_ns(parts[0]), (float(parts[1]), float(parts[2]), float(parts[3]))

    rows = read_rows(path, parse, "timestamp ax ay az")
    return sorted(rows, key=lambda r: r[0])


def _check_size(path: Path, img: np.ndarray, intr: Intrinsics) -> None:
    if img.shape[:2] != (intr.height, intr.width):
        raise InputError(f"{path}: {img.shape[1]}x{img.shape[0]}, calibration is {intr.width}x{intr.height}")
