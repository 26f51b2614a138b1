"""The IMU: its samples and files, the synthetic IMU, the tracker's estimates against the synthetic
truth, and the pipeline keeping a pose through a textureless stretch (INERTIAL) where vision alone
is LOST; a session's log replays with its IMU to the same bytes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import octolog

from octolog.kit.errors import InputError
from octolog.kit.imu import GRAVITY_MS2, D455, ImuNoise, read_imu_txt, unite
from octolog.kit.mcaplog import read_wire
from octolog.kit.metrics import read_tum
from octolog.replay.synthetic import SyntheticScene
from octolog.replay.synthetic_imu import simulate, true_motion
from octolog.schemas import codec
from octolog.schemas.topics import TRACKING_STATUS
from octolog.tracker.inertial import Inertial
from scipy.spatial.transform import Rotation

FPS = 30
BLANK_FRAMES = 150  # 5 s: 3 s tracked with the IMU, the 1.5 s stretch, 0.5 s tracked again after it
BLANK_AT_S, BLANK_S = 3.0, 1.5  # the textureless stretch of the pipeline runs below
BLANK_SOURCE = f"synthetic:{BLANK_FRAMES}:imu=200:blank={BLANK_AT_S:g}+{BLANK_S:g}"


def test_imu_txt_is_read_and_a_bad_line_is_named(tmp_path):
    path = tmp_path / "imu.txt"
    path.write_text("# t wx wy wz ax ay az\n1.000 0.1 0.2 0.3 0 9.8 0\n1.005 0.1 0.2 0.3 0 9.8 0.5\n")
    s = read_imu_txt(path)
    assert s.stamp_ns.tolist() == [1_000_000_000, 1_005_000_000]
    assert s.gyro[1].tolist() == [0.1, 0.2, 0.3] and s.accel[1].tolist() == [0.0, 9.8, 0.5]
    path.write_text("1.000 0.1 0.2 0.3 0 9.8 0\n1.005 0.1 0.2 oops 0 9.8 0\n")
    with pytest.raises(InputError, match=r"imu.txt:2: want 'timestamp wx wy wz ax ay az'"):
        read_imu_txt(path)
    path.write_text("1.000 0.1 0.2 0.3 0 9.8 0\n0.990 0.1 0.2 0.3 0 9.8 0\n")
    with pytest.raises(InputError, match="stamps must increase"):
        read_imu_txt(path)


def test_unite_puts_the_accelerometer_on_the_gyros_stamps():
    g_ns = np.array([0, 5, 10, 15], np.int64)
    a_ns = np.array([0, 10], np.int64)
    s = unite(g_ns, np.ones((4, 3)), a_ns, np.array([[0.0, 0.0, 0.0], [10.0, 20.0, 30.0]]))
    assert s.accel[:, 0].tolist() == [0.0, 5.0, 10.0, 10.0]  # interpolated, held past the last
    assert s.stamp_ns.tolist() == g_ns.tolist()


def _spin(rate: float):
    """A camera at rest in place, turning about world z at `rate` rad/s (optical z along world x at t=0)."""
    optical = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

    def trajectory(t):
        t = np.asarray(t, float)
        rot = Rotation.from_euler("z", rate * t[:, None]).as_matrix() @ optical
        return np.zeros((len(t), 3)), rot
    return trajectory


def test_the_synthetic_imu_measures_gravity_and_the_turn_rate():
    gyro, force = true_motion(_spin(1.5), np.linspace(0.0, 2.0, 9))
    # world z (the turn axis, and up) is the optical frame's -y
    np.testing.assert_allclose(gyro, np.tile([0.0, -1.5, 0.0], (9, 1)), atol=1e-6)
    np.testing.assert_allclose(force, np.tile([0.0, -GRAVITY_MS2, 0.0], (9, 1)), atol=1e-5)
    quiet = ImuNoise(0.0, 0.0, 0.0, 0.0)
    sim = simulate(_spin(1.5), 1.0, 200.0, quiet, 3, 0)
    np.testing.assert_allclose(sim.samples.gyro - sim.gyro_bias, np.tile([0.0, -1.5, 0.0], (len(sim.samples), 1)),
                               atol=1e-6)


def test_a_synthetic_imu_sample_does_not_depend_on_the_sequence_length():
    short, long = (SyntheticScene(n_frames=n, imu_hz=200.0).simulated_imu for n in (30, 90))
    n = len(short.samples)
    assert np.array_equal(short.samples.gyro, long.samples.gyro[:n])
    assert np.array_equal(short.samples.accel, long.samples.accel[:n])


@pytest.mark.parametrize("motion", ["loop", "turns"])
def test_the_imus_estimates_converge_on_the_synthetic_truth(motion):
    """Fed the true poses and the simulated D455 IMU (turn-on biases and random walk), the gyro's
    bias comes within 20 % of the truth, gravity within a degree, each frame's propagated pose
    within 5 mm of the truth, and the gyro's rotation between keyframes (the back end's factor)
    within three of its sigmas of the true rotation once the bias is known."""
    scene = SyntheticScene(n_frames=360, motion=motion, imu_hz=200.0, seed=7)
    sim = scene.simulated_imu
    imu = Inertial(noise=D455)
    errors, keyframe_z = [], []
    for i in range(360):
        stamp = scene.stamp_ns(i)
        imu.add(sim.samples.between(stamp - 50_000_000 if i == 0 else scene.stamp_ns(i - 1), stamp))
        _, propagated = imu.step_to(stamp)
        if propagated is not None:
            errors.append(np.linalg.norm(propagated[:3, 3] - scene.pose(i)[:3, 3]))
        if i % 8 == 0:
            factor = imu.keyframe_rotation(i // 8, stamp)
            assert (factor is None) == (i == 0)
            if factor is not None and i >= 120:
                prev, R, sigma = factor
                true = scene.pose(i - 8)[:3, :3].T @ scene.pose(i)[:3, :3]
                assert prev == i // 8 - 1 and sigma < np.radians(0.5)
                keyframe_z.append(Rotation.from_matrix(R.T @ true).magnitude() / sigma)
        imu.observe(stamp, scene.pose(i))
    assert keyframe_z and max(keyframe_z) < 3.0, keyframe_z  # |error| / sigma, 3-dof: 99 % below 3.4
    truth = sim.gyro_bias[-1]
    assert np.linalg.norm(imu.bg - truth) < 0.2 * np.linalg.norm(truth), (imu.bg, truth)
    up = imu.gravity / np.linalg.norm(imu.gravity)
    assert np.degrees(np.arccos(np.clip(-up[2], -1, 1))) < 1.0, imu.gravity  # world z is up here
    assert errors and max(errors) < 0.005


@pytest.mark.parametrize("off_deg", [0.0, 30.0, 90.0])
def test_vision_overrules_a_gyro_whose_axes_are_wrong(off_deg):
    """Told a camera-IMU rotation 30 or 90 degrees off (a calibration for another mounting, axes
    swapped), the gyro's rotations disagree with vision's: it predicts nothing, propagates nothing
    and gives the back end no factor (the tracker drops those it gave). The right one is confirmed
    and gives a factor at every keyframe."""
    scene = SyntheticScene(n_frames=90, motion="turns", imu_hz=200.0, seed=3)
    sim = scene.simulated_imu
    wrong = np.eye(4)
    wrong[:3, :3] = Rotation.from_rotvec(np.radians(off_deg) * np.array([0.6, 0.8, 0.0])).as_matrix()
    imu = Inertial(wrong, noise=D455)
    factors = []
    for i in range(90):
        stamp = scene.stamp_ns(i)
        imu.add(sim.samples.between(stamp - 50_000_000 if i == 0 else scene.stamp_ns(i - 1), stamp))
        _, propagated = imu.step_to(stamp)
        if i % 6 == 0:
            factors.append(imu.keyframe_rotation(i // 6, stamp))
        imu.observe(stamp, scene.pose(i))
    confirmed = off_deg == 0.0
    assert imu.gyro_trusted == imu.gyro_confirmed == confirmed
    assert all(f is not None for f in factors[2:]) if confirmed else all(f is None for f in factors[-5:])
    if not confirmed:
        assert propagated is None or not imu.trusted


def _status_states(session) -> list[int]:
    return [codec.decode(m.data, TRACKING_STATUS.msgtype).state
            for m in read_wire(session / "session.mcap", [TRACKING_STATUS.name])]


def _drift_over_stretch(session) -> float:
    """Largest position error over the stretch, relative to the last pose before it (truth alike)."""
    est, gt = read_tum(session / "trajectory.txt"), read_tum(session / "groundtruth.txt")
    t0 = est.stamps_ns[0]
    rel = (est.stamps_ns - t0) * 1e-9
    before = int(np.flatnonzero(rel < BLANK_AT_S)[-1])
    during = np.flatnonzero((rel >= BLANK_AT_S) & (rel < BLANK_AT_S + BLANK_S))
    g_index = {int(s): k for k, s in enumerate(gt.stamps_ns)}

    def pose(tr, k):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(tr.quats_xyzw[k]).as_matrix()
        T[:3, 3] = tr.positions[k]
        return T

    def rel_pose(tr, k, k0):
        return np.linalg.inv(pose(tr, k0)) @ pose(tr, k)

    b_gt = g_index[int(est.stamps_ns[before])]
    return max(np.linalg.norm(rel_pose(est, k, before)[:3, 3] - rel_pose(gt, g_index[int(est.stamps_ns[k])], b_gt)[:3, 3])
               for k in during)


def test_the_pipeline_keeps_a_pose_from_the_imu_through_a_textureless_stretch(octolog_run):
    """Through the real processes: every frame of the blank 1.5 s is INERTIAL (none LOST), the pose
    drifts less than 5 cm over it, and tracking takes up again from it (no relocalisation)."""
    out, stdout = octolog_run(BLANK_SOURCE)
    codes = codec.msgtype(TRACKING_STATUS.msgtype)
    states = _status_states(out)
    assert states.count(codes.LOST) == 0
    assert states.count(codes.INERTIAL) == round(BLANK_S * FPS)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["imu"]["inertial_frames"] == round(BLANK_S * FPS)
    assert "IMU: used" in stdout
    assert "IMU: used" in octolog("info", str(out)).stdout  # the session folder says so too
    assert _drift_over_stretch(out) < 0.05
    assert len(read_tum(out / "trajectory.txt").stamps_ns) == BLANK_FRAMES


def test_without_the_imu_the_textureless_stretch_is_lost(octolog_run):
    out, stdout = octolog_run(BLANK_SOURCE, "--set", "tracker.imu=false")
    codes = codec.msgtype(TRACKING_STATUS.msgtype)
    states = _status_states(out)
    assert states.count(codes.INERTIAL) == 0
    assert states.count(codes.LOST) >= round(BLANK_S * FPS) - 1
    assert json.loads((out / "summary.json").read_text())["imu"] is None
    assert "IMU: none" in stdout


def test_the_map_stands_on_the_imus_gravity(octolog_run):
    """The mapper builds `map` on the tracker's IMU estimate of up (tracker/gravity), at least twice
    closer to the room's true up than the accelerometer's mean at the first frame, which the run
    without the IMU takes; the session's config keeps it for its replays."""
    import tomllib

    from octolog.replay.sources import open_source

    with_imu, _ = octolog_run(BLANK_SOURCE)
    without, _ = octolog_run(BLANK_SOURCE, "--set", "tracker.imu=false")
    truth = open_source(BLANK_SOURCE).scene.pose(0)[:3, :3].T @ np.array([0.0, 0.0, 1.0])

    def error_deg(out):
        up = np.asarray(tomllib.loads((out / "config.toml").read_text())["mapper"]["grid_up"], float)
        return np.degrees(np.arccos(np.clip(up @ truth / np.linalg.norm(up), -1.0, 1.0)))
    assert "the tracker's IMU estimate" in json.loads((with_imu / "map_stats.json").read_text())["map_frame"]["note"]
    assert error_deg(with_imu) < error_deg(without) / 2, (error_deg(with_imu), error_deg(without))


def test_a_session_with_an_imu_replays_from_its_log_to_the_same_bytes(octolog_run, tmp_path):
    out, _ = octolog_run(BLANK_SOURCE)
    again = tmp_path / "again"
    octolog("run", "--source", f"mcap:{out / 'session.mcap'}", "--out", str(again), "--quiet", "--rerun", "off")
    for name in ("trajectory.txt", "map.bt"):
        assert (again / name).read_bytes() == (out / name).read_bytes(), name


def test_a_tum_folders_imu_is_placed_and_clocked_by_its_calibration(tmp_path):
    """imu.txt beside the images, a calibration file with the IMU's pose on the camera, its clock
    offset and noise: the replay publishes the samples on the camera's clock in the IMU's frame,
    the transform in the camera's tree and the noise in the camera's properties; the tracker's
    side finds the same transform in that tree."""
    from helpers.recordings import make_tum

    from octolog.kit.tftree import StaticTree
    from octolog.replay.imu import IMU_FRAME, source_imu, source_imu_noise
    from octolog.replay.node import camera_tree
    from octolog.replay.sources import open_source
    from octolog.schemas import posemsgs, streammsgs
    from octolog.tracker.node import camera_from_imu

    folder = make_tum(tmp_path / "seq")
    (folder / "imu.txt").write_text("".join(f"{100.0 + k / 200:.6f} 0.1 0 0 0 -9.8 0\n" for k in range(40)))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    T[:3, 3] = [0.03, 0.0, -0.01]
    rows = ", ".join("[" + ", ".join(f"{v:.17g}" for v in row) + "]" for row in T)
    cal = tmp_path / "cam.toml"
    cal.write_text(f"width = 64\nheight = 48\nfx = 60.0\nfy = 60.0\ncx = 31.5\ncy = 23.5\n"
                   f"camera_from_imu = [{rows}]\nimu_time_offset_ms = 2.5\nimu_gyro_noise = 1e-3\n"
                   "imu_accel_noise = 1e-2\nimu_gyro_walk = 1e-4\nimu_accel_walk = 1e-3\n")
    source = open_source(f"tum:{folder}", camera=str(cal))
    imu = source_imu(source)
    assert imu.frame_id == IMU_FRAME and imu.samples.stamp_ns[0] == 100_002_500_000
    tree = StaticTree()
    tree.add(posemsgs.tf_msg(camera_tree(source, "camera_color_optical_frame"), 0))
    np.testing.assert_allclose(camera_from_imu(tree, "camera_color_optical_frame", IMU_FRAME), T, atol=1e-12)
    props = codec.decode(codec.encode(streammsgs.camera_properties_msg("cam", 0.0, imu_noise=source_imu_noise(source)),
                                      "octolog_msgs/msg/CameraProperties"), "octolog_msgs/msg/CameraProperties")
    assert streammsgs.imu_noise_from(props) == ImuNoise(1e-3, 1e-2, 1e-4, 1e-3)
    cal.write_text(cal.read_text().replace("imu_gyro_walk = 1e-4\n", ""))
    with pytest.raises(InputError, match="'imu_gyro_walk' missing"):
        open_source(f"tum:{folder}", camera=str(cal))
