"""Calibration files (kit/calibration.py): a camera the source does not name, given explicitly.

A TUM folder whose name says no camera, and an MCAP recording without CameraInfo, run with
`replay.camera=FILE.toml`; everything the tracker needs (intrinsics, distortion, depth scale,
readout) comes from the file, and a bad file is one line naming the key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers.recordings import SMALL, layout_mcap, make_tum

from octolog.kit import depthmodel
from octolog.kit.calibration import load_calibration
from octolog.kit.depthmodel import DepthModel
from octolog.kit.errors import InputError
from octolog.replay.sources import open_source

CAL = """name = "lab-xtion"
width = 64
height = 48
fx = 50.0
fy = 51.0
cx = 31.5
cy = 23.5
distortion = [0.1, -0.2, 0.0, 0.0, 0.05]
depth_scale_m = 0.0001
readout_ms = 12.5
"""


def _cal(tmp_path: Path, text: str = CAL) -> str:
    path = tmp_path / "cam.toml"
    path.write_text(text)
    return str(path)


def test_a_tum_folder_without_a_camera_name_runs_with_a_calibration_file(tmp_path):
    folder = make_tum(tmp_path / "my_sequence", n=4)
    with pytest.raises(InputError, match="replay.camera=CAMERA.toml"):
        open_source(f"tum:{folder}")
    source = open_source(f"tum:{folder}", camera=_cal(tmp_path))
    frame = next(iter(source.frames()))
    k = frame.intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (64, 48, 50.0, 51.0, 31.5, 23.5)
    assert k.distortion == (0.1, -0.2, 0.0, 0.0, 0.05) and frame.depth_scale_m == 0.0001
    assert source.readout_s == 0.0125
    assert next(iter(source.encoded_frames())).depth_scale_m == 0.0001  # what the wire carries


def test_an_mcap_recording_without_camera_info_runs_with_a_calibration_file(tmp_path):
    rec = tmp_path / "r.mcap"
    layout_mcap(rec, info=False)
    with pytest.raises(InputError, match="missing calibration.*replay.camera=CAMERA.toml"):
        open_source(f"mcap:{rec}")
    cal = _cal(tmp_path, CAL.replace("width = 64", f"width = {SMALL.width}").replace("height = 48",
                                                                                    f"height = {SMALL.height}"))
    source = open_source(f"mcap:{rec}", camera=cal)
    frame = next(iter(source.frames()))
    assert frame.intrinsics.fx == 50.0 and frame.depth_scale_m == 0.0001 and source.readout_s == 0.0125
    assert np.asarray(frame.depth).dtype == np.uint16


@pytest.mark.parametrize(("edit", "message"), [
    (lambda t: t.replace("fx = 50.0\n", ""), "'fx' missing"),
    (lambda t: t.replace("fy = 51.0", "fy = -1"), "'fy' = -1: want a positive number"),
    (lambda t: t.replace("width = 64", "width = 64.5"), "whole pixels"),
    (lambda t: t.replace("readout_ms = 12.5", "readout_ms = 500"), "'readout_ms' = 500: want 0..100 ms"),
    (lambda t: t.replace("distortion = [0.1, -0.2, 0.0, 0.0, 0.05]", "distortion = [1, 2]"), "'distortion'"),
    (lambda t: t + "fov = 90\n", "unknown calibration key 'fov'"),
    (lambda t: t.replace("fx = 50.0", "fx = nan"), "'fx' = nan"),
    (lambda t: t.replace("name =", "name"), "invalid TOML"),
    (lambda t: t + "depth_baseline_m = 0.05\n", "depth_disparity_sigma_px missing"),
    (lambda t: t + "depth_baseline_m = 0\ndepth_disparity_sigma_px = 0.1\n", "depth_baseline_m = 0.0: want a positive"),
    (lambda t: t + "depth_baseline_m = 0.05\ndepth_disparity_sigma_px = 'x'\n", "depth_disparity_sigma_px = 'x'"),
])
def test_a_bad_calibration_file_is_one_line_naming_the_key(tmp_path, edit, message):
    with pytest.raises(InputError, match=message) as err:
        load_calibration(_cal(tmp_path, edit(CAL)))
    assert "\n" not in str(err.value) and "cam.toml" in str(err.value)


def test_replay_camera_takes_a_calibration_file_only_where_it_means_something(tmp_path):
    from octolog.kit.errors import ConfigError

    with pytest.raises(ConfigError, match="replay.camera"):
        open_source("synthetic:5", camera=_cal(tmp_path))


def test_the_depth_error_model_comes_from_the_calibration_file_or_the_camera_the_source_names(tmp_path):
    """Baseline, focal length (default fx) and disparity noise from the file's keys; a TUM folder's
    freiburg camera is the Kinect model; a file without the keys leaves the model unknown."""
    folder = make_tum(tmp_path / "my_sequence", n=2)
    given = open_source(f"tum:{folder}", camera=_cal(tmp_path, CAL + "depth_baseline_m = 0.05\n"
                                                                 "depth_disparity_sigma_px = 0.1\n"))
    assert given.depth_model == DepthModel(0.05, 50.0, 0.1)
    assert open_source(f"tum:{folder}", camera=_cal(tmp_path)).depth_model is None
    tum = open_source(f"tum:{make_tum(tmp_path / 'rgbd_dataset_freiburg1_x', n=2)}")
    assert tum.depth_model == depthmodel.KINECT
    # what the model says: Khoshelham and Elberink's Kinect, 1.4 mm at 1 m and 3.6 cm at 5 m
    assert depthmodel.KINECT.sigma_m(1.0) == pytest.approx(1.43e-3, rel=0.01)
    assert depthmodel.KINECT.sigma_m(5.0) == pytest.approx(0.0357, rel=0.01)
    assert depthmodel.realsense("Intel RealSense D435I", 213.0).baseline_m == 0.050
    assert depthmodel.realsense("Orbbec Astra", 570.0) is None


def test_the_imu_a_session_measured_goes_into_a_calibration_file(tmp_path):
    """`imu.toml` (kit/calibration.py: imu_keys) appended to a camera's calibration file loads back
    as what was measured: the IMU's place, its clock offset and its noise."""
    from octolog.kit.calibration import imu_keys
    from octolog.kit.imu import ImuNoise
    from octolog.replay.synthetic_imu import mismatch_rotation

    placed = np.eye(4)
    placed[:3, :3] = mismatch_rotation(4.0)
    placed[:3, 3] = [0.01, -0.005, 0.02]
    noise = ImuNoise(2.1e-3, 1.9e-2, 1.7e-4, 3.3e-3)
    cal = load_calibration(_cal(tmp_path, CAL + imu_keys(placed, -7.25, noise)))
    assert np.allclose(cal.camera_from_imu, placed, atol=1e-8)
    assert cal.imu_time_offset_s == pytest.approx(-7.25e-3)
    assert cal.imu_noise == noise
    assert "imu_time_offset_ms = 0.000" in imu_keys(None, -0.0, None)
