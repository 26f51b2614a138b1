"""The tracker process: RGB-D frames in, a pose and status per frame and keyframes out."""

from __future__ import annotations

import functools
import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
import dataclasses
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Self

import numpy as np

from octolog.kit.bus import Bus, BusConfig, Publisher, Received
from octolog.kit.config import to_dict
from octolog.kit.cpuclock import charge
from octolog.kit.errors import InputError, TrackingError
from octolog.kit.geometry import Intrinsics, RgbdFrame, invert
from octolog.kit.metrics import write_tum
from octolog.kit.tftree import StaticTree
from octolog.kit.viz import Viz
from octolog.schemas import codec, posemsgs, rgbdmsgs, streammsgs, wirecompression
from octolog.schemas.msgtypes import CameraPropertiesMsg, CompressedRgbdFrameMsg, RgbdFrameMsg, TrackingStatusMsg
from octolog.schemas.topics import (
    BACKEND_DEFERRED,
    CAMERA_PROPERTIES,
    CONFIGS,
    FRAMES_TAKEN,
    KEYFRAME,
    KEYFRAME_COMPRESSED,
    KEYFRAME_END,
    KEYFRAME_POSES,
    POSE,
    RGBD,
    RGBD_COMPRESSED,
    RGBD_END,
    TF,
    TF_STATIC,
    TRACKER_GRAVITY,
    TRACKING_STATUS,
    TRAJECTORY,
)
from octolog.tracker.config import TrackerConfig
from octolog.tracker.depth_bias import DepthBias
from octolog.tracker.factory import make_odometry, set_depth_model, set_readout
from octolog.tracker.imu_intake import IMU_TOPICS
from octolog.tracker.intake import FRAME_PRODUCERS, Decoded, Intake
from octolog.tracker.interface import Tracker, TrackingState, TrackResult

log = logging.getLogger(__name__)


def status_code(state: TrackingState) -> int:
    """The `TrackingStatus.state` code of a state: the message's constant of the same name."""
    return int(getattr(codec.msgtype(TRACKING_STATUS.msgtype), state.value))


@dataclass
class TrackerRunSummary:
    """What one tracker run did, frame counts by outcome: the summary `track` returns."""
    frames: int = 0
    tracked: int = 0
    lost: int = 0
    skipped: int = 0  # live mode: not processed, a newer frame was waiting
    backend_deferred: int = 0  # live mode: keyframes that went in while the back end was busy
    rejected: int = 0  # undecodable or inconsistent frames
    problems: list[str] = field(default_factory=list)  # why each rejected frame was
    keyframes: int = 0
    loops: int = 0
    relocalisations: int = 0
    inertial: int = 0  # frames whose pose came from the IMU alone (INERTIAL)
    imu: dict | None = None  # what the IMU did (tracker/inertial.py: InertialState); None: no samples
    stamps_ns: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)
    depth_bias: DepthBias | None = None  # the camera's depth error as the final map has it
    # with a saved map (tracker.map): its keyframes, the frame the camera was found at in it (-1:
    # never), and whether the tracker gave it up for a map of its own
    prior: dict | None = None
    # no first keyframe: the most corners with depth any frame had, and tracking.min_init_points
    uninitialised: dict | None = None


def run(cfg: TrackerConfig, bus_cfg: BusConfig, *, trajectory: Path | None = None, rerun: str = "off",
        recording_id: str = "octolog", save_map: Path | None = None) -> TrackerRunSummary:
    odometry = make_odometry(cfg)
    with Bus(bus_cfg, "tracker") as bus:
        with Viz(rerun, "tracker", recording_id) as viz:
            result = track(odometry, cfg, bus, viz)
        _conclude(odometry, cfg, result, trajectory, save_map)  # while the mapper finishes the map
        # a mapper that joins late, or starts again, recovers every keyframe from this stage's history:
        # it stays until the mapper is done
        bus.wait_for(cfg.keep_for, cfg.wait_timeout_s)
        for stage in _kept_for(cfg):
            bus.linger(stage)
    return result


def _kept_for(cfg: TrackerConfig) -> list[str]:
    """The stages the tracker keeps its keyframes for: a mapper if one comes (it may restart), and
    `keep_for`, waited for."""
    return list(dict.fromkeys(["mapper", *cfg.keep_for]))


def _conclude(odometry: Tracker, cfg: TrackerConfig, result: TrackerRunSummary, trajectory: Path | None,
              save_map: Path | None) -> None:
    """The run's findings into `result`; the saved SLAM map and the trajectory file written."""
    if cfg.map:
        result.prior = {"map": cfg.map, "mode": cfg.mode, "keyframes": odometry.prior_keyframes,
                        "found_at_frame": odometry.prior_found_at, "frames_before": odometry.prior_misses,
                        "dropped": odometry.prior_dropped, "placed_keyframes": odometry.prior_placed,
                        **odometry.prior_counts(), "relocalised": result.relocalisations}
    if not result.keyframes and getattr(odometry, "init_best", -1) >= 0:
        result.uninitialised = {"best_points": odometry.init_best,
                                "min_init_points": odometry.params.tracking.min_init_points}
    if save_map is not None and hasattr(odometry, "save_map") and result.tracked:
        odometry.save_map(save_map)
    if trajectory is not None:
        # native: every tracked frame through the final pose of its keyframe, so what BA and loop
        # closing corrected reaches the whole trajectory (LOST frames have no pose to give)
        write_tum(trajectory, *odometry.trajectory())


class _Outputs:
    """What the tracker publishes: per frame its pose, status and TF, keyframes, loop corrections and
    deferred back-end jobs; at the end the final poses, the trajectory and the end counts."""

    def __init__(self, bus: Bus, cfg: TrackerConfig) -> None:
        self.bus = bus
        self.pose, self.status, self.tf = bus.publisher(POSE), bus.publisher(TRACKING_STATUS), bus.publisher(TF)
        self.kf = KeyframeOut(bus, cfg.wire_compression)
        self.kf_end = bus.publisher(KEYFRAME_END)
        self.poses = bus.publisher(KEYFRAME_POSES)
        self.deferred = bus.publisher(BACKEND_DEFERRED)
        self.gravity = bus.publisher(TRACKER_GRAVITY)
        self.held: dict[int, RgbdFrame] = {}  # frames of keyframes not yet placed in the saved map, by seq

    def up(self, odometry: Tracker, stamp_ns: int, *, final: bool = False) -> None:
        """The IMU's up in `world` for the mapper's `map` frame: the first estimate once the IMU is
        trusted, and (`final`) the session's, after the last keyframe (tracker/inertial.py: Inertial.up)."""
        if self.gravity.count and not final:
            return
        up = getattr(odometry, "imu_up", None)
        if up is not None:
            self.gravity.put(posemsgs.vector3_stamped_msg(up, stamp_ns, "world"))

    def untracked(self, msg: RgbdFrameMsg | CompressedRgbdFrameMsg, state: TrackingState,
                  imu_mark: tuple[int, int] = (0, 0)) -> None:
        """A frame skipped or rejected: its status only."""
        self.status.put(_status(msg.seq, codec.stamp_ns(msg.header), state, False, -1, 0, 0, 0.0, imu_mark=imu_mark))

    def tracked(self, frame: RgbdFrame, res: TrackResult, tree: StaticTree, ms: float,
                result: TrackerRunSummary, imu_mark: tuple[int, int] = (0, 0)) -> None:
        self.pose.put(posemsgs.pose_stamped_msg(res.world_from_camera, frame.stamp_ns))
        # world -> the camera tree's root (camera_link), so each frame keeps one parent (REP 105)
        root, root_from_camera = tree.root_from(frame.frame_id)
        world_from_root = res.world_from_camera @ invert(root_from_camera)
        self.tf.put(posemsgs.tf_msg([("world", root, world_from_root)], frame.stamp_ns))
        if res.corrected:  # a loop closed, or the depth correction changed: the mapper moves those keyframes
            self.poses.put(posemsgs.keyframe_poses_msg(res.corrected, frame.stamp_ns, res.depth_inverse_offset))
        result.loops += res.loop is not None
        result.relocalisations += res.relocalised
        if res.hold:  # a keyframe of a map not placed yet (tracker/slam.py: SavedMapSearch): sent once it is
            self.held[frame.seq] = frame
        for kf_id, (seq, pose) in sorted(res.placed.items()):
            kept = self.held[seq]
            self.kf.put(kf_id, pose, replace(kept, depth_inverse_offset=res.depth_inverse_offset))
            result.keyframes += 1
        if res.placed:
            self.held.clear()
        if res.is_keyframe:
            self.kf.put(res.keyframe_id, res.world_from_camera,
                        replace(frame, depth_inverse_offset=res.depth_inverse_offset) if res.depth_inverse_offset else frame)
            result.keyframes += 1
        if res.backend_deferred:  # on record: a replay of this run defers at the same frame
            self.deferred.put(codec.msgtype(BACKEND_DEFERRED.msgtype)(data=json.dumps(
                {"seq": frame.seq, "keyframe_id": res.keyframe_id, "stamp_ns": frame.stamp_ns})))
            result.backend_deferred += 1
        self.status.put(_status(frame.seq, frame.stamp_ns, res.state, res.is_keyframe, res.keyframe_id,
                                res.n_matches, res.n_inliers, ms, res.map_moved_m, res.relocalised, imu_mark))

    def finish(self, odometry: Tracker, result: TrackerRunSummary) -> None:
        # the back end's last word: every keyframe at its final pose, so the map matches the
        # trajectory. Sent before the end messages, whose count for it the mapper waits for.
        t0 = time.monotonic()
        moved = odometry.finish()
        log.info("the back end's last job and the final adjustment: %.2f s, %d of %d keyframes moved",
                 time.monotonic() - t0, len(moved), odometry.n_keyframes)
        if moved:
            self.poses.put(posemsgs.keyframe_poses_msg(odometry.keyframe_poses(), result.stamps_ns[-1],
                                                       getattr(odometry, "depth_offset", 0.0)))
        # the whole trajectory at its final poses, for a log on another machine (the file is local)
        stamps, poses = odometry.trajectory()
        self.bus.publisher(TRAJECTORY).put(posemsgs.path_msg(stamps, poses))
        if stamps:
            self.up(odometry, int(stamps[-1]), final=True)
        self.kf_end.put(streammsgs.stream_end_msg(TRAJECTORY.name, 1))
        self.kf_end.put(streammsgs.stream_end_msg(KEYFRAME_POSES.name, self.poses.count))
        self.kf_end.put(streammsgs.stream_end_msg(self.kf.topic_name, self.kf.count))


def track(odometry: Tracker, cfg: TrackerConfig, bus: Bus, viz: Viz) -> TrackerRunSummary:
    out = _Outputs(bus, cfg)
    # frames come raw or compressed, whichever the source publishes; decoding is the same call
    warm_up()
    if (worker := getattr(odometry, "worker", None)) is not None:
        worker.ready()  # its imports done before the stream: not competing for the cores with the first frames
    tree = StaticTree()  # the camera's own frames, from whoever knows the camera (recorder, replay)
    bus.listen(TF_STATIC, tree.add)
    imu_topics = list(IMU_TOPICS) if cfg.imu and hasattr(odometry, "add_imu") else []
    bus.start([RGBD, RGBD_COMPRESSED, RGBD_END, CAMERA_PROPERTIES, *imu_topics], wait_for=cfg.wait_for,
              timeout_s=cfg.wait_timeout_s)
    bus.publisher(CONFIGS["tracker"]).put(streammsgs.config_msg("tracker", to_dict(cfg)))
    bus.watch(FRAME_PRODUCERS)  # whichever sends the frames: a replay, or a recorder publishing live
    # a mapper may restart, or join late: keep its keyframes until it is done
    bus.watch(_kept_for(cfg), required=False)
    result = TrackerRunSummary()
    expected: int | None = None
    with Intake(bus, odometry, viz=viz.enabled, live=cfg.live, lag_ms=cfg.live_lag_ms) as intake, \
            VizLog(viz) as shown:
        while expected is None or result.frames < expected:
            if (item := intake.get()) is None:
                if expected is not None:
                    bus.expect_count(RGBD, result.frames, expected)
                continue
            r, prep = item
            if r.topic == CAMERA_PROPERTIES:
                use_camera(odometry, cfg, r.decode())
                continue
            if r.topic == RGBD_END:
                expected = int(r.decode().count)
                bus.expect_count(RGBD, result.frames, expected)
                continue
            result.frames += 1
            if cfg.live and intake.behind(r):
                far = odometry.n_keyframes > YOUNG_MAP_KEYFRAMES and intake.behind(r, FAR_BEHIND)
                r, prep = _skip_behind(intake, r, prep, out, result, far=far)
            mark = _feed_imu(odometry, intake, r, tree) if imu_topics else (0, 0)
            _track_frame(odometry, cfg, functools.partial(intake.prepared, r, prep), out, tree, result, shown, mark)
    # every frame is in: a live camera may close while the last adjustment runs (its producer gone
    # from here on is no loss)
    for producer in FRAME_PRODUCERS:
        bus.unwatch(producer)
    bus.say_taken(FRAMES_TAKEN)
    out.finish(odometry, result)
    estimate = getattr(odometry, "depth_bias", None)  # the native tracker's; ORB-SLAM3 has none
    result.depth_bias = estimate() if estimate is not None else None
    if (imu := getattr(odometry, "imu_state", None)) is not None:
        result.imu = {**dataclasses.asdict(imu), "inertial_frames": result.inertial}
    if result.depth_bias is not None:
        viz.text("tracker/events", result.depth_bias.summary())
    return result


# live: more than this many times `tracker.live_lag_ms` behind, the newest frame wins at once ...
FAR_BEHIND = 4.0
# ... once the map has more keyframes than this: a young map has nowhere to relocalise into, so a gap
# of several frames in a fast first turn lost it for good (ORB-SLAM resets a map this young instead)
YOUNG_MAP_KEYFRAMES = 5


def _skip_behind(intake: Intake, r: Received, prep: Future[Decoded] | None, out: _Outputs, result: TrackerRunSummary,
                 *, far: bool) -> tuple[Received, Future[Decoded] | None]:
    """Stay real-time, on record: behind, this frame is skipped for the next one, never two in a row
    (a tracked frame is at most two camera frames after the last: a fast turn stays trackable,
    where jumping to the newest made gaps of several frames and lost track); `far` behind, the
    newest waiting frame wins and every older one is skipped, so latency stays bounded (a skipped
    frame's IMU samples go to the next frame tracked)."""
    while (newer := intake.newer_frame()) is not None:
        intake.skip(r)
        out.untracked(r.decode(), TrackingState.SKIPPED)
        result.skipped += 1
        result.frames += 1
        r, prep = newer
        if not far:
            break
    return r, prep


def _track_frame(odometry: Tracker, cfg: TrackerConfig, prepare: Callable[[], Decoded], out: _Outputs,
                 tree: StaticTree, result: TrackerRunSummary, shown: VizLog, imu_mark: tuple[int, int] = (0, 0)) -> None:
    """One frame through the tracker and out to the bus and the viewer; a frame that cannot be
    tracked at all is consumed and reported LOST (`prepare`: the frame's decoding and features, timed with it)."""
    t0 = time.perf_counter()
    msg, frame_or_error, prepared = prepare()
    try:
        if isinstance(frame_or_error, InputError):
            raise frame_or_error
        frame = frame_or_error
        with charge("tracking"):
            res = odometry.track(frame, prepared)
    except (InputError, TrackingError) as exc:
        # an undecodable frame, or one that contradicts its camera (size, depth type, changed
        # intrinsics), is consumed and reported LOST, never a crash
        result.rejected += 1
        result.problems.append(f"frame {msg.seq}: {exc}")
        out.untracked(msg, TrackingState.LOST, imu_mark)
        return
    if cfg.throttle_ms:
        time.sleep(max(0.0, cfg.throttle_ms / 1e3 - (time.perf_counter() - t0)))
    ms = (time.perf_counter() - t0) * 1e3
    result.ms.append(ms)
    result.stamps_ns.append(frame.stamp_ns)
    result.poses.append(res.world_from_camera)
    result.tracked += res.state == TrackingState.OK
    result.lost += res.state == TrackingState.LOST
    result.inertial += res.state == TrackingState.INERTIAL
    out.tracked(frame, res, tree, ms, result, imu_mark)
    out.up(odometry, frame.stamp_ns)
    shown.put(frame, res, result, odometry)


# odometry: Any, a Tracker with an IMU (`add_imu`, `imu_state`), which the caller checks with hasattr
def _feed_imu(odometry: Any, intake: Intake, r: Received, tree: StaticTree) -> tuple[int, int]:
    """The IMU samples that came before frame `r` (and skipped frames before it), to the tracker;
    with the first, where the IMU sits on the camera (the camera's /tf_static; none: the IMU's axes
    are the colour camera's). Returns the samples taken so far per stream, for the record."""
    samples, mark = intake.imu_before(r)
    if len(samples) and odometry.imu_state is None:
        odometry.set_camera_from_imu(camera_from_imu(tree, r.decode().header.frame_id, intake.imu.frame_id))
    odometry.add_imu(samples)
    return mark


def camera_from_imu(tree: StaticTree, camera_frame: str, imu_frame: str) -> np.ndarray:
    """camera_from_imu (4x4) from the static tree; the identity if it does not join the two frames."""
    if not imu_frame or imu_frame == camera_frame:
        return np.eye(4)
    root_c, root_from_camera = tree.root_from(camera_frame)
    root_i, root_from_imu = tree.root_from(imu_frame)
    return invert(root_from_camera) @ root_from_imu if root_c == root_i else np.eye(4)


def warm_up() -> None:
    """Every message the tracker takes and sends through its codec once, on a tiny blank frame: the
    lazy set-up (each type's CDR code, the pose conversions' imports) then happens before the stream,
    not on the first frames. Live, a first frame that took half a second (this machine: 450 ms)
    held back the camera's next frames at every start."""
    pose, wire = np.eye(4), wirecompression.WireCompression("png")
    frame = RgbdFrame(0, 0, np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8), np.uint16), 1e-3,
                      Intrinsics(8, 8, 8.0, 8.0, 4.0, 4.0))
    zstd = wirecompression.WireCompression("jpeg", depth="zstd")  # a live recorder's frames
    for topic, msg in ((RGBD, rgbdmsgs.rgbd_msg(frame)), (RGBD_COMPRESSED, rgbdmsgs.compressed_rgbd_msg(frame, wire)),
                       (RGBD_COMPRESSED, rgbdmsgs.compressed_rgbd_msg(frame, zstd))):
        rgbdmsgs.rgbd_from_msg(codec.decode(codec.encode(msg, topic.msgtype), topic.msgtype))
    for topic, msg in ((TRACKING_STATUS, _status(0, 0, TrackingState.OK, False, -1, 0, 0, 0.0)),
                       (POSE, posemsgs.pose_stamped_msg(pose, 0)),
                       (TF, posemsgs.tf_msg([("world", "camera_link", pose)], 0)),
                       (KEYFRAME, rgbdmsgs.keyframe_msg(0, pose, frame)),
                       (KEYFRAME_COMPRESSED, rgbdmsgs.compressed_keyframe_msg(0, pose, frame, wire)),
                       (KEYFRAME_POSES, posemsgs.keyframe_poses_msg({0: pose})),
                       (TRAJECTORY, posemsgs.path_msg([0], [pose])),
                       (KEYFRAME_END, streammsgs.stream_end_msg(TRAJECTORY.name, 0)),
                       (BACKEND_DEFERRED, codec.msgtype(BACKEND_DEFERRED.msgtype)(data=""))):
        codec.encode(msg, topic.msgtype)


def use_camera(odometry: Tracker, cfg: TrackerConfig, props: CameraPropertiesMsg) -> None:
    """The stream's camera properties: its depth error model (kit/depthmodel.py), its IMU's noise, its readout unless
    the config sets one (then a warning if they disagree), so a tracker on another machine tracks as
    `octolog run` does."""
    set_depth_model(odometry, streammsgs.depth_model_from(props))
    if (noise := streammsgs.imu_noise_from(props)) is not None and hasattr(odometry, "set_imu_noise"):
        odometry.set_imu_noise(noise)
    if cfg.rolling_shutter_ms is None:
        set_readout(odometry, props.readout_s)
    elif abs(cfg.rolling_shutter_ms - props.readout_s * 1e3) > 1e-6:
        log.warning("tracker.rolling_shutter_ms = %g but the camera (%s) reads out in %g ms; using %g (the local "
                    "setting)", cfg.rolling_shutter_ms, props.camera, props.readout_s * 1e3, cfg.rolling_shutter_ms)


class KeyframeOut:
    """Keyframes onto the bus, raw or compressed. `wire_compression` "source": with the images the
    frame came with (compressed frames give compressed keyframes, not re-encoded; raw give raw);
    else as wirecompression.parse_wire_compression says. The topic is fixed by the first keyframe."""

    def __init__(self, bus: Bus, wire_compression: str) -> None:
        self.bus = bus
        self.forward = wire_compression == wirecompression.SOURCE
        self.wire = wirecompression.parse_wire_compression(wire_compression)
        self.pub: Publisher | None = None

    @property
    def count(self) -> int:
        return 0 if self.pub is None else self.pub.count

    @property
    def topic_name(self) -> str:
        return (KEYFRAME if self.pub is None else self.pub.topic).name

    def put(self, kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame) -> None:
        forwarded = self.forward and "wire" in frame.extra
        if self.pub is None:
            self.pub = self.bus.publisher(KEYFRAME_COMPRESSED if forwarded or self.wire else KEYFRAME)
        if forwarded and self.pub.topic is KEYFRAME_COMPRESSED:
            self.pub.put(rgbdmsgs.forwarded_keyframe_msg(kf_id, world_from_camera, frame))
        elif self.pub.topic is KEYFRAME_COMPRESSED:  # a raw frame among compressed ones: lossless
            wire = self.wire or wirecompression.WireCompression("png")
            self.pub.put(rgbdmsgs.compressed_keyframe_msg(kf_id, world_from_camera, frame, wire))
        else:
            self.pub.put(rgbdmsgs.keyframe_msg(kf_id, world_from_camera, frame))


def _status(seq: int, stamp: int, state: TrackingState, is_kf: bool, kf_id: int, n_matches: int, n_inliers: int,
            ms: float, map_moved_m: float = 0.0, relocalised: bool = False, imu_mark: tuple[int, int] = (0, 0)
            ) -> TrackingStatusMsg:
    return codec.msgtype(TRACKING_STATUS.msgtype)(
        header=codec.header(stamp, "world"), seq=seq, state=status_code(state), is_keyframe=is_kf,
        keyframe_id=kf_id, n_matches=n_matches, n_inliers=n_inliers, processing_ms=ms, map_moved_m=map_moved_m,
        relocalised=relocalised, imu_gyro_count=imu_mark[0], imu_accel_count=imu_mark[1])


# keypoint colours by KeypointState: unmatched grey, rejected red, tracked green, new map point blue
KP_COLOURS = np.array([[160, 160, 160], [230, 40, 40], [40, 220, 60], [40, 140, 255]], np.uint8)


@dataclass(frozen=True)
class _Shown:
    """What one frame's Rerun log needs, taken on the tracking thread before the next frame changes it."""

    frame: RgbdFrame
    res: TrackResult
    first: bool
    first_keyframe: bool
    ms: float
    poses: list[np.ndarray] | None  # at keyframes: every tracked pose so far
    keypoints: tuple[np.ndarray, np.ndarray] | None
    local_map: np.ndarray | None  # at keyframes


class VizLog:
    """The tracker's Rerun logging off the tracking thread: one thread logs the frames in
    their order; the tracking thread hands each frame over with copies of what its log reads of the
    tracker. A full queue holds the tracking thread back rather than lose a frame's log. An error in
    logging is raised when the block ends, as it was raised where it happened before."""

    QUEUE = 8

    def __init__(self, viz: Viz) -> None:
        self.viz = viz
        self._q: queue.Queue[_Shown | None] = queue.Queue(self.QUEUE)
        self._thread = threading.Thread(target=self._run, name="tracker-viz", daemon=True)
        self.error: BaseException | None = None
        self._keyframe_shown = False  # the keyframe camera's pinhole goes with the first keyframe logged

    def __enter__(self) -> Self:
        if self.viz.enabled:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._thread.is_alive():
            self._q.put(None)
            self._thread.join()
        if self.error is not None and exc[0] is None:
            raise self.error

    def put(self, frame: RgbdFrame, res: TrackResult, result: TrackerRunSummary, odometry: Tracker) -> None:
        if not self.viz.enabled:
            return
        kp = odometry.keypoints()
        first_keyframe, self._keyframe_shown = res.is_keyframe and not self._keyframe_shown, \
            self._keyframe_shown or res.is_keyframe
        self._q.put(_Shown(frame, res, result.frames == 1, first_keyframe, result.ms[-1],
                           list(result.poses) if res.is_keyframe else None,
                           None if kp is None else (kp[0].copy(), kp[1].copy()),
                           odometry.local_map() if res.is_keyframe else None))

    def _run(self) -> None:
        while (item := self._q.get()) is not None:
            try:
                with charge("rerun"):
                    _log(self.viz, item)
            except BaseException as exc:  # noqa: BLE001  (kept, raised on the tracking thread at the end)
                self.error = self.error or exc


KEYFRAME_DEPTH_STEP = 2  # the viewer's keyframe depth: every n-th pixel in each direction


def _every(intr: Intrinsics, step: int) -> Intrinsics:
    """The camera of an image that keeps every `step`-th pixel of `intr`'s in each direction."""
    return replace(intr, width=-(-intr.width // step), height=-(-intr.height // step), fx=intr.fx / step,
                   fy=intr.fy / step, cx=intr.cx / step, cy=intr.cy / step)


def _log(viz: Viz, shown: _Shown) -> None:
    frame, res = shown.frame, shown.res
    viz.set_time(frame.stamp_ns, frame.seq)
    if shown.first:
        viz.camera("world/tracker/camera", frame.intrinsics)
    viz.pose("world/tracker/camera", res.world_from_camera)
    colour, _ = frame.extra.get("wire", (None, None))
    jpeg = colour.data if colour is not None and "jpeg" in colour.format else frame.extra.get("jpeg")
    viz.rgb("world/tracker/camera/image", frame.rgb, jpeg)  # the one place the images are logged
    viz.scalar("tracker/inliers", float(res.n_inliers))
    if shown.keypoints is not None:
        pts, state = shown.keypoints
        viz.points2d("world/tracker/camera/image/keypoints", pts, KP_COLOURS[state])
    viz.scalar("tracker/ms", shown.ms)
    if shown.poses is not None:
        # the whole path, re-sent at keyframes only: per frame it would cost O(frames) each time
        viz.path3d("world/tracker/trajectory", np.array([p[:3, 3] for p in shown.poses]), color=[255, 160, 0])
        viz.points3d("world/tracker/keyframes", np.array([res.world_from_camera[:3, 3]]), [0, 200, 255],
                     radius=0.02)
        viz.text("tracker/events", f"keyframe {res.keyframe_id} at frame {frame.seq}")
        # the keyframe's depth at the keyframe's pose (per frame it would add 100 kB a frame and
        # nothing a keyframe does not show); its own entity, so it stays where it was taken. Every
        # KEYFRAME_DEPTH_STEP-th pixel: the full image's PNG was the largest part of a live tracker's
        # Rerun logging; the map's dense cloud shows the keyframes whole
        if shown.first_keyframe:
            viz.camera("world/tracker/keyframe", _every(frame.intrinsics, KEYFRAME_DEPTH_STEP))
        viz.pose("world/tracker/keyframe", res.world_from_camera)
        viz.depth("world/tracker/keyframe/depth", frame.depth[::KEYFRAME_DEPTH_STEP, ::KEYFRAME_DEPTH_STEP],
                  frame.depth_scale_m)
        if shown.local_map is not None:
            viz.points3d("world/tracker/local_map", shown.local_map, [255, 255, 255], radius=0.004)
    if res.loop is not None:
        viz.text("tracker/events", f"loop closed: keyframe {res.loop[0]} with keyframe {res.loop[1]}, "
                                   f"{len(res.corrected)} keyframes moved")
        viz.points3d("world/tracker/keyframes", np.array([T[:3, 3] for _, T in sorted(res.corrected.items())]),
                     [0, 200, 255], radius=0.02)
    if res.relocalised:
        viz.text("tracker/events", f"relocalised at frame {frame.seq}")
    if res.state == TrackingState.INERTIAL:
        viz.text("tracker/events", f"frame {frame.seq}: no visual fix, the pose is the IMU's (INERTIAL)")
