"""The simulated D455 (shell/simcamera.py): the room filmed along one known path. Its depth lies on
the room's surfaces, seen from the depth imager; its IMU turns and accelerates as the path does; its
frames are the same bytes whether rendered now or read from the cache; the recording it makes
carries the path as ground truth, and a live session on it reports the ATE and a trusted IMU."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers import octolog
from scipy.spatial.transform import Rotation

from octolog.kit import metrics
from octolog.kit.imu import GRAVITY_MS2
from octolog.recorder.capture import CaptureProfile
from octolog.recorder.software_d455 import simulated_layout
from octolog.replay import depth_noise
from octolog.replay.sources import open_source
from octolog.replay.synthetic import SyntheticScene
from octolog.shell import simcamera

SMALL = CaptureProfile(color=(424, 240, 30), depth=(424, 240, 30))  # D455 profiles, cheap to render
LAYOUT = simulated_layout(SMALL, 200, 100)
FRAMES = 3


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A cache with the first FRAMES frames of the walk at SMALL (the room's textures take ~9 s)."""
    root = tmp_path_factory.mktemp("simcache")
    camera = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT), FRAMES, root)
    assert camera.render() == FRAMES
    return root


def test_depth_lies_on_the_room_seen_from_the_depth_imager(cache):
    camera = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT), FRAMES, cache)
    room = SyntheticScene(n_frames=1)
    d = LAYOUT.depth
    u, v = np.meshgrid(np.arange(d.width), np.arange(d.height))
    for i in range(FRAMES):
        z = camera.depth(i).astype(np.float64) * LAYOUT.depth_units_m
        ok = z > 0
        assert 0.8 < ok.mean() < 0.999  # holes along edges and dropouts, not many
        pts = np.stack([(u - d.cx) / d.fx * z, (v - d.cy) / d.fy * z, z, np.ones_like(z)], axis=-1)[ok]
        world_from_depth = camera.world_from_color(np.array([camera.frame_time_s(i)]))[0] @ np.asarray(
            LAYOUT.color_from_depth)
        off = room.distance_to_surface((pts @ world_from_depth.T)[:, :3])
        # the D455's disparity noise in depth (z² sigma / f b), plus the 1 mm step and the surface's slant
        s = depth_noise.SENSORS["d455"]
        sigma = z[ok] ** 2 * s.sigma_px / (d.fx * s.baseline_m)
        assert np.mean(off <= 4 * sigma + 0.002) > 0.99
        # from the colour camera's pose instead, the same depth would be 59 mm off the surfaces
        wrong = (pts @ camera.world_from_color(np.array([camera.frame_time_s(i)]))[0].T)[:, :3]
        assert np.median(room.distance_to_surface(wrong)) > 0.01


def test_frames_are_the_same_bytes_from_the_cache_and_rendered_cold(cache, tmp_path):
    hit = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT), FRAMES, cache)
    assert hit.missing() == [] and hit.render() == 0  # nothing left to render
    cold = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT), 2, tmp_path)
    assert cold.render() == 2
    for i in range(2):
        assert cold.path(i).read_bytes() == hit.path(i).read_bytes()
    assert not list(tmp_path.rglob("*.tmp*"))  # each frame renamed into place whole
    # another option is another cache entry; the IMU's are not cached (computed as the camera runs)
    assert simcamera.SceneOptions(LAYOUT, depth_bias_px=0.1).key() != hit.options.key()
    assert simcamera.SceneOptions(LAYOUT, imu_time_offset_ms=5.0, imu_rotation_deg=1.0).key() == hit.options.key()


def _rotation(camera, t):
    return (camera.world_from_color(np.array([t]))[0] @ camera.true_color_from_imu())[:3, :3]


@pytest.mark.parametrize("turned_deg", [0.0, 5.0])
def test_the_imu_turns_and_feels_gravity_as_the_path_does(turned_deg):
    camera = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT, motion="turns", imu_rotation_deg=turned_deg), 60)
    # the gyro, integrated over half a second of a head turn (each sample standing for the 5 ms around
    # it), gives the IMU's own turn (within its turn-on bias, under 1 deg/s)
    rates = np.array([camera.motion("gyro", k) for k in range(100, 200)], np.float64)
    turned = Rotation.identity()
    for w in rates:
        turned = turned * Rotation.from_rotvec(w / 200.0)
    t0, t1 = 0.5 - 0.0025, 1.0 - 0.0025
    truth = Rotation.from_matrix(_rotation(camera, t0).T @ _rotation(camera, t1))
    assert truth.magnitude() > math.radians(30)
    assert (truth.inv() * turned).magnitude() < math.radians(1.0)
    # the IMU turned from its calibration: the gyro no longer reads in the calibrated frame
    calibrated = camera.layout.color_from_imu[:3, :3]
    placed = Rotation.from_matrix((camera.world_from_color(np.array([t0]))[0][:3, :3] @ calibrated).T
                                  @ camera.world_from_color(np.array([t1]))[0][:3, :3] @ calibrated)
    assert ((placed.inv() * turned).magnitude() < math.radians(1.0)) == (turned_deg == 0.0)


def test_the_accelerometer_feels_gravity_in_the_imus_frame():
    camera = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT), 60)
    # gravity, the walk's small accelerations (~0.2 m/s²) and a turn-on bias (under 0.2 m/s²)
    force = np.array([camera.motion("accel", k) for k in range(100)], np.float64)
    up = np.array([_rotation(camera, k / 100.0).T @ [0.0, 0.0, GRAVITY_MS2] for k in range(100)])
    assert np.median(np.linalg.norm(force - up, axis=1)) < 0.5


def test_the_imu_stamps_lag_the_camera_by_the_offset():
    late = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT, motion="turns", imu_time_offset_ms=20.0), 60)
    on_time = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT, motion="turns"), 60)
    # the same noise draws: sample k of the late IMU is on-time sample k + 4 (20 ms at 200 Hz) but for them
    a = np.array([late.motion("gyro", k) for k in range(100, 200)])
    b = np.array([on_time.motion("gyro", k + 4) for k in range(100, 200)])
    c = np.array([on_time.motion("gyro", k) for k in range(100, 200)])
    assert np.abs(a - b).max() < 0.03 < 0.1 < np.abs(a - c).max()


def test_a_recording_carries_the_ground_truth_to_a_replay(cache, tmp_path):
    out = tmp_path / "r.mcap"
    octolog("record", str(out), "--backend", "software", "--color", "424x240@30", "--depth", "424x240@30",
            "--set", f"software.frames={FRAMES}", "--quiet", env={simcamera.CACHE_ENV: str(cache)})
    source = open_source(f"mcap:{out}")
    truth = metrics.parse_tum(source.groundtruth_tum(), "ground truth")
    assert [f.stamp_ns for f in source.frames()] == truth.stamps_ns.tolist()
    camera = simcamera.SceneCamera(simcamera.SceneOptions(LAYOUT), FRAMES, cache)
    assert source.groundtruth_tum() == camera.groundtruth_tum()


@pytest.mark.slow
def test_a_live_session_on_the_simulated_camera_reports_ate_and_trusts_its_imu(tmp_path):
    """`octolog run --source d455:software` for a few seconds of the walk at 424x240: the summary has
    the ATE against the path the camera filmed, and the IMU trusted (after its first second and the
    30 frames it must agree with vision on)."""
    out = tmp_path / "live"
    sets = ["--set", "recorder.color.width=424", "--set", "recorder.color.height=240",
            "--set", "recorder.depth.width=424", "--set", "recorder.depth.height=240"]
    octolog("run", "--source", "d455:software", "--duration", "4", "--out", str(out), "--quiet", "--rerun", "off",
            *sets, env={simcamera.CACHE_ENV: str(tmp_path / "cache")}, timeout=600)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ate"]["pairs"] == summary["tracked_frames"] > 30
    assert summary["ate"]["rmse_m"] < 0.02
    assert summary["imu"]["trusted_frames"] > 0
