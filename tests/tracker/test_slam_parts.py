"""Each part of the SLAM core (tracker/slam.py composes them) built and checked alone.

Frames come from the synthetic room (replay/synthetic.py): real renders with exact depth, so a
part's answer can be checked against the geometry without running the whole tracker.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from octolog.kit.errors import TrackingError
from octolog.kit.geometry import RgbdFrame, invert
from octolog.kit.imu import ImuSamples
from octolog.replay.sources import open_source
from octolog.tracker.backend import BackendResult
from octolog.tracker.backend_handoff import BackendHandoff
from octolog.tracker.config import OdometryParams, TrackerConfig
from octolog.tracker.depth_bias import DepthBias
from octolog.tracker.depth_correction import DepthCorrection
from octolog.tracker.features import FrameFeatures
from octolog.tracker.front_end import FrontEnd
from octolog.tracker.imu_fusion import ImuFusion
from octolog.tracker.interface import KeypointState
from octolog.tracker.local_map import LocalMap, TrackedFrame
from octolog.tracker.map_tracking import MapTracker
from octolog.tracker.motion import MAX_PREDICTION_STEPS, MotionModel
from octolog.tracker.pose import so3_exp
from octolog.tracker.trajectory import Trajectory

FRAME_NS = 33_333_333


@pytest.fixture(scope="module")
def params() -> OdometryParams:
    return TrackerConfig().odometry_params()


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    return list(open_source("synthetic:8").frames())


def _moved(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, np.radians(yaw_deg), 0.0]))
    T[:3, 3] = (x, y, z)
    return T


def _first_keyframe(params: OdometryParams, frame: RgbdFrame) -> tuple[FrontEnd, LocalMap, FrameFeatures]:
    """A front end and a local map holding `frame` as keyframe 0 at the origin."""
    front, local = FrontEnd(params), LocalMap(params)
    feats = front.features(frame, front.extract(frame, None, map_made=False), 0.0)
    empty = np.zeros(0, np.int64)
    local.insert(frame.seq, np.eye(4), feats, TrackedFrame(np.eye(4), empty, empty, 0, 0, feats))
    return front, local, feats


def _tracker_over_first_keyframe(params: OdometryParams, frame: RgbdFrame) -> tuple[FrontEnd, LocalMap, MapTracker]:
    """A pose fit over a map of `frame` alone, the camera last seen at the origin."""
    front, local, _ = _first_keyframe(params, frame)
    motion = MotionModel()
    motion.remember(frame.stamp_ns, np.eye(4))
    return front, local, MapTracker(params, front, local, motion)


# -- the motion model ----------------------------------------------------------------------------


def test_motion_model_predicts_at_constant_velocity_up_to_its_limit() -> None:
    motion = MotionModel()
    motion.remember(0, np.eye(4))
    assert np.array_equal(motion.predict(FRAME_NS), np.eye(4))  # no velocity yet: stays
    motion.remember(FRAME_NS, _moved(x=0.01, yaw_deg=1.0))
    two = motion.predict(2 * FRAME_NS)
    assert two[0, 3] == pytest.approx(0.02 * np.cos(np.radians(0.5)), abs=1e-3)
    far = motion.predict(100 * FRAME_NS)  # a stall: extrapolated at most MAX_PREDICTION_STEPS intervals
    assert np.linalg.norm(far[:3, 3]) < 0.01 * (MAX_PREDICTION_STEPS + 1.5)
    assert motion.continuous(2 * FRAME_NS) and motion.tracked
    motion.lost()
    assert motion.continuous(3 * FRAME_NS) and not motion.continuous(10 * FRAME_NS)
    motion.remember(20 * FRAME_NS, np.eye(4), continuous=False)  # found again: the velocity is unknown
    assert motion.velocity is None


def test_motion_model_moves_and_scales_with_the_map() -> None:
    motion = MotionModel()
    motion.remember(0, np.eye(4))
    motion.remember(FRAME_NS, _moved(x=0.1))
    motion.move(_moved(y=1.0))
    assert np.allclose(motion.last_pose[:3, 3], (0.1, 1.0, 0.0))
    motion.scale(2.0)
    assert np.allclose(motion.last_pose[:3, 3], (0.2, 2.0, 0.0))
    assert np.allclose(motion.velocity[1], (0.2, 0.0, 0.0))


def test_trajectory_follows_its_keyframes() -> None:
    local_pose = _moved(x=1.0)

    class _Kf:
        id, world_from_camera = 0, local_pose

    traj = Trajectory()
    traj.add(5, _Kf, _moved(x=1.5))  # type: ignore[arg-type]
    _Kf.world_from_camera = _moved(x=2.0)  # the keyframe moves: the frame with it
    stamps, poses = traj.poses([_Kf])  # type: ignore[list-item]
    assert stamps == [5] and np.allclose(poses[0][:3, 3], (2.5, 0, 0))
    traj.scale(2.0)
    assert np.allclose(traj.poses([_Kf])[1][0][:3, 3], (3.0, 0, 0))  # type: ignore[list-item]


# -- the front end and the local map ------------------------------------------------------------


def test_front_end_reads_depth_and_corrects_it(params, frames) -> None:
    front = FrontEnd(params)
    extracted = front.extract(frames[0], None, map_made=False)
    plain = front.features(frames[0], extracted, 0.0)
    assert len(plain) > 500 and plain.has_depth.sum() > 0.8 * len(plain)
    assert front.kp_state.shape == (len(plain),) and not front.kp_state.any()
    corrected = front.features(frames[0], extracted, 0.02)  # 1/z <- 1/z - 0.02: every reading longer
    has = plain.z > 0
    assert np.all(corrected.z[has] > plain.z[has]) and np.array_equal(corrected.z[~has], plain.z[~has])
    prepared = front.prepare(frames[1])
    assert prepared is not None and prepared[0] is frames[1]
    assert front.extract(frames[1], prepared, map_made=True) is prepared[1]


def test_front_end_refuses_another_camera_once_a_map_is_made(params, frames) -> None:
    front = FrontEnd(params)
    front.extract(frames[0], None, map_made=False)
    other = replace(frames[1], intrinsics=replace(frames[1].intrinsics, fx=frames[1].intrinsics.fx * 1.1))
    front.extract(other, None, map_made=False)  # no map yet: the new camera is taken
    with pytest.raises(TrackingError, match="intrinsics"):
        front.extract(frames[1], None, map_made=True)


def test_local_map_inserts_points_and_asks_for_keyframes_by_motion(params, frames) -> None:
    front, local, feats = _first_keyframe(params, frames[0])
    near = (feats.z > 0) & (feats.z <= params.depth.max_new_point_m)
    assert len(local) == 1 and local.points.size == int(near.sum())
    ids = local.local_points(np.eye(4))
    assert ids.size == local.points.size
    uv, inside = local.project(ids, np.eye(4), front.intrinsics)
    assert inside.mean() > 0.95
    # every point seen again, from where the keyframe stands: nothing new
    kp = np.flatnonzero(near)
    again = TrackedFrame(np.eye(4), kp, local.keyframes[0].obs_pid[: kp.size], kp.size, kp.size, feats)
    assert not local.need_keyframe(np.eye(4), again)
    assert local.need_keyframe(_moved(x=params.keyframes.translation_m * 2), again)


def test_a_saved_point_seen_from_afar_weighs_less_in_a_pose_fit_than_one_seen_from_close():
    """map_tracking.point_sigmas: a point fused from one reading at 3 m, localized in from 1 m, is
    known to 9x the error of one read at 1 m: its residuals' sigmas widen (pixels and inverse
    depth); one read many times from close by keeps the keypoint's own sigmas."""
    from octolog.tracker.keyframe_map import depth_weight
    from octolog.tracker.map_tracking import point_sigmas

    K = np.array([[525.0, 0.0, 320.0], [0.0, 525.0, 240.0], [0.0, 0.0, 1.0]])
    pts = np.array([[0.0, 0.0, 1.0]] * 3)
    weight = np.array([depth_weight(np.array([3.0]))[0], depth_weight(np.array([1.0]))[0], 1e12])
    own = np.ones(3)
    inv_px, inv_d = point_sigmas(weight, pts, np.eye(4), K, own, 0.002)
    assert inv_px[0] < inv_px[1] < inv_px[2] and inv_d[0] < inv_d[1] < inv_d[2]
    assert inv_px[2] == pytest.approx(1.0) and inv_d[2] == pytest.approx(1.0 / 0.002)
    assert 1.0 / inv_px[0] == pytest.approx(np.hypot(1.0, 525.0 * 0.002 * 9.0), rel=1e-9)


def test_a_pose_graph_holds_every_fixed_keyframe():
    """kit/posegraph: several fixed keyframes (a saved map's) stay where they are; a loop edge that
    disagrees with them moves only the free ones."""
    from octolog.kit.posegraph import optimize_pose_graph

    poses = np.stack([_moved(x=0.1 * i) for i in range(4)])
    edges = [(i, i + 1, np.linalg.inv(poses[i]) @ poses[i + 1], 1.0) for i in range(3)]
    edges.append((0, 3, _moved(x=0.25), 1.0))  # says keyframe 3 is 5 cm nearer
    out = optimize_pose_graph(poses, edges, fixed=range(2))
    assert np.array_equal(out[0], poses[0]) and np.array_equal(out[1], poses[1])
    assert out[3][0, 3] < 0.3 - 0.01


# -- the pose fit --------------------------------------------------------------------------------


def test_map_tracker_finds_a_pose_from_a_wrong_prediction(params, frames) -> None:
    front, local, tracker = _tracker_over_first_keyframe(params, frames[0])
    feats = front.features(frames[0], front.extract(frames[0], None, map_made=True), 0.0)
    tracked = tracker.track(feats, _moved(x=0.03, yaw_deg=1.0), frames[0].stamp_ns)  # 3 cm, 1 deg off
    assert tracked is not None and tracked.n_inliers > 300
    assert np.abs(invert(tracked.camera_from_world) - np.eye(4)).max() < 2e-3
    assert tracker.last_inlier_ids.size == tracked.n_inliers
    assert (front.kp_state == KeypointState.TRACKED).sum() == tracked.n_inliers
    blank = FrameFeatures(uv=feats.uv[:5], octave=feats.octave[:5], desc=feats.desc[:5], z=feats.z[:5], xyz=feats.xyz[:5])
    assert tracker.track(blank, np.eye(4), frames[0].stamp_ns) is None  # too few features: no pose


# -- the back end's hand-off, the depth correction, the IMU ----------------------------------------


def test_backend_handoff_runs_a_job_and_applies_it_once(params, frames) -> None:
    front, local, tracker = _tracker_over_first_keyframe(params, frames[0])
    feats = front.features(frames[4], front.extract(frames[4], None, map_made=True), 0.0)
    tracked = tracker.track(feats, np.eye(4), frames[4].stamp_ns)
    assert tracked is not None
    local.insert(frames[4].seq, invert(tracked.camera_from_world), tracked.feats, tracked)
    handoff = BackendHandoff(params, local)  # inline: no worker
    assert handoff.sync() == ({}, None, None)  # nothing pending
    handoff.submit(front.K)
    assert isinstance(handoff.pending, BackendResult)
    assert not handoff.defer(frames[5].seq)  # a replay never lets a keyframe in without the result
    moved, loop, delta = handoff.sync()
    assert loop is None and delta is not None and delta.shape == (4, 4) and handoff.pending is None
    assert handoff.sync()[2] is None


def test_depth_correction_moves_the_map_by_the_bias_found(params, frames) -> None:
    _, local, feats = _first_keyframe(params, frames[0])
    local.keyframes[0].world_from_camera[:3, 3] = (1.0, 0.0, 0.0)
    local.reindex_poses()
    depth = DepthCorrection(params)
    assert depth.found(local) is None  # correct_bias is off by default, and the map is small
    before = local.points.xyz[: local.points.size].copy()
    s = depth.correct(local, DepthBias(inverse_offset=0.01, sigma=1e-4, scale=1.05, points=1, readings=1))
    assert s == 1.05 and depth.offset == pytest.approx(params.depth.inverse_offset + 0.01) and depth.corrections == 1
    assert np.allclose(local.keyframes[0].world_from_camera[:3, 3], (1.05, 0, 0))
    assert np.allclose(local.kf_pos[0], (1.05, 0, 0))
    far = local.keyframes[0].feats.z > 0
    assert np.all(local.keyframes[0].feats.z[far] > feats.z[far])  # the readings re-corrected
    assert not np.allclose(local.points.xyz[: local.points.size], before)


def test_imu_fusion_without_samples_changes_nothing() -> None:
    motion = MotionModel()
    motion.remember(0, np.eye(4))
    imu = ImuFusion(motion)
    predicted = _moved(x=0.01)
    out, propagated = imu.predict(predicted, FRAME_NS)
    assert out is predicted and propagated is None and imu.rotation_prior is None
    assert not imu.rejects(np.eye(4), propagated) and not imu.coasts(propagated)
    assert imu.state is None and imu.up is None and imu.keyframe_rotation(0, 0, []) is None
    samples = ImuSamples(np.array([1, 2, 3], np.int64) * 5_000_000, np.zeros((3, 3)), np.tile((0.0, -9.81, 0.0), (3, 1)))
    off = ImuFusion(motion, enabled=False)  # tracker.imu = false: samples are not even kept
    off.add(samples)
    assert off.state is None and off.inertial is None
    on = ImuFusion(motion)
    on.add(samples)
    assert on.inertial is not None


def test_young_points_that_move_together_do_not_pull_the_pose(params, frames) -> None:
    """A keyframe's points on a person walking by move with them for the next frames: the pose is
    fitted to the established points (seen from two keyframes), and the young ones that agree."""
    front, local, tracker = _tracker_over_first_keyframe(params, frames[0])
    feats = front.features(frames[0], front.extract(frames[0], None, map_made=True), 0.0)
    pts = local.points
    n = pts.size
    kept = local.keyframes[0]
    uv = kept.feats.uv[kept.obs_kp]  # where each point was made
    person = np.zeros(n, bool)
    person[kept.obs_pid[uv[:, 0] < 260]] = True  # the left of the view: a person, young points ...
    pts.n_obs[:n] = np.where(person, 1, 2)  # ... the rest seen from two keyframes
    pts.xyz[:n][person] += (0.02, 0.0, 0.0)  # the person has moved 2 cm since the keyframe
    tracked = tracker.track(feats, _moved(x=0.01), frames[0].stamp_ns)
    assert tracked is not None
    assert np.abs(invert(tracked.camera_from_world)[:3, 3]).max() < 1e-3  # the camera did not move
    pulled = tracker.solve(feats, *tracker._guided(feats, np.arange(n), tracked.camera_from_world, 4.0)[:2],
                           tracked.camera_from_world, use_ransac=False)
    assert pulled is not None and np.linalg.norm(invert(pulled[0])[:3, 3]) > params.tracking.young_pull_m  # pulled along
