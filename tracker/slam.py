"""RGB-D SLAM: ORB features tracked against a local map of keyframe points, keyframes, and a back
end (local bundle adjustment, loop closing) on snapshots of the map.

Per frame (`RgbdSlam.track`): extract ORB features spread over the image and read their depth
(tracker/front_end.py), predict the pose with a constant-velocity model (tracker/motion.py) and the
gyro (tracker/imu_fusion.py), fit it against the local map's points (tracker/map_tracking.py),
decide on a keyframe and insert it (tracker/local_map.py), hand the map to the back end and apply
its last result (tracker/backend_handoff.py), correct the depth camera's bias (tracker/
depth_correction.py). Each part owns its state; this module composes them and holds nothing else
but the saved-map search (tracking in a map an earlier session saved, `--map`).

The core sees only `RgbdFrame`s and one `OdometryParams` (no configuration tree, no I/O, no clock),
and is deterministic: the same frames give byte-identical poses in any process.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.depthmodel import DepthModel
from octolog.kit.errors import TrackingError
from octolog.kit.geometry import RgbdFrame, invert
from octolog.kit.imu import ImuNoise, ImuSamples
from octolog.tracker.backend_handoff import BackendHandoff
from octolog.tracker.config import OdometryParams, TrackerConfig
from octolog.tracker.depth_bias import DepthBias
from octolog.tracker.depth_correction import DepthCorrection, recorrected
from octolog.tracker.features import FrameFeatures
from octolog.tracker.front_end import Extracted, FrontEnd
from octolog.tracker.imu_fusion import ImuFusion
from octolog.tracker.inertial import InertialState
from octolog.tracker.interface import KeypointState, TrackingState, TrackResult
from octolog.tracker.local_map import LocalMap, TrackedFrame
from octolog.tracker.map_tracking import MapTracker
from octolog.tracker.mapfile import SavedMap, save_map
from octolog.tracker.motion import MotionModel, scaled
from octolog.tracker.trajectory import Trajectory
from octolog.tracker.vocab import Vocabulary
from octolog.tracker.worker import Worker


@dataclass
class SavedMapSearch:
    """Where the camera stands in a saved map (`RgbdSlam.adopt_map`).

    Until the camera is found in the map, every frame is tried by place recognition alone and
    reported LOST, while a map of its own (`sandbox`, a second `RgbdSlam`) tracks it in its own
    world; the keyframes it makes are held back (`TrackResult.hold`: the node keeps their frames).
    Found, at frame f, the held map is placed in the saved one by the two poses of frame f
    (world_from_own = saved pose @ own pose^-1): its keyframes, numbered after the saved ones, and
    its points join the map, the frames it tracked join the trajectory, and the held keyframes go
    out at their placed poses (`TrackResult.placed`); tracking goes on in the saved map's world and,
    in `map` mode, extends it. Not found within `map_find_frames` frames, the tracker gives the
    saved map up: the held map becomes the map (its keyframes go out numbered from 0, in its own
    world: `dropped`). The saved map's keyframes and points are frozen (`LocalMap.frozen_keyframes`):
    the back end moves only the new ones, so the tracking lives in the saved map's world; once found,
    each frame is fitted to the local map's points and the saved map's points in view
    (`MapTracker.locate(with_saved=True)`, these weighed by their own depth error).

    In `localize` mode nothing of the saved map changes, and the camera is looked for until the
    stream ends. The keyframes tracking makes are temporary: they carry the camera where the view
    leaves the saved map (visual odometry on points that are not the map's), the back end ties them
    to the saved map (bundle adjustment around its frozen keyframes, loops, the final adjustment for
    the trajectory), and they never leave the tracker (no keyframe is published, held or saved). A
    tracked frame is `localized` when at least `tracking.min_inliers` of its inliers are the saved
    map's points, else `carried` by the temporary ones (or the IMU)."""

    keyframes: int = 0  # keyframes the saved map brought
    found_at: int = -1  # the frame seq the camera was first found at in it (-1: not yet, or no map)
    misses: int = 0  # frames not found in it before that
    dropped: bool = False  # not found within map_find_frames: tracking went on in a map of its own
    placed: int = 0  # keyframes of the map of its own placed in the saved one when found
    sandbox: RgbdSlam | None = None  # the map of its own while the camera is not found
    held: dict[int, int] = field(default_factory=dict)  # its keyframes: id -> frame seq
    localized: int = 0  # frames after found whose pose rests on the saved map's points
    carried: int = 0  # frames after found tracked on the temporary points alone, or by the IMU
    lost: int = 0  # frames after found with no pose


class RgbdSlam:
    """RGB-D SLAM: frame-to-local-map tracking, keyframe insertion and the back end (loop closing, bundle
    adjustment). Call `track` once per frame, in time order, and `finish` at the end of the stream.

    `params` (default: `TrackerConfig()`'s) holds every tunable, by part: features, depth gating,
    matching and pose fitting (`tracking`), keyframes, the local map, local and final bundle
    adjustment, loop closing, relocalisation. `params.readout_s` is the colour camera's
    rolling-shutter readout time (0: global shutter): keypoints are moved to mid-readout with the
    camera's velocity. With a `vocabulary`, loop and relocalisation candidates come from a
    bag-of-words index over it (the best `params.bow_candidates`), else every keyframe is a
    candidate. `background` runs the back end in a worker process (outputs are identical either
    way). One instance per camera stream; not thread-safe, but for `prepare`, which one other thread
    may call ahead of `track`.
    """

    def __init__(self, params: OdometryParams | None = None, *, vocabulary: Vocabulary | None = None,
                 background: bool | Worker = False, defer_backend: int = 0,
                 backend_deferred_at: frozenset[int] = frozenset()) -> None:
        params = params if params is not None else TrackerConfig().odometry_params()
        self._params = params
        self.front = FrontEnd(params)
        self.motion = MotionModel()
        self.imu = ImuFusion(self.motion, enabled=params.imu, max_inertial_s=params.max_inertial_s)
        self.map = LocalMap(params, vocabulary)
        self.tracker = MapTracker(params, self.front, self.map, self.motion)
        worker = background if isinstance(background, Worker) else Worker() if background else None
        self.backend = BackendHandoff(params, self.map, worker=worker, defer_backend=defer_backend,
                                      backend_deferred_at=backend_deferred_at)
        self.depth = DepthCorrection(params)
        self.frames = Trajectory()
        self.saved = SavedMapSearch()
        self.init_best = -1  # before the first keyframe: the most corners with depth a frame had

    @property
    def params(self) -> OdometryParams:
        return self._params

    @params.setter
    def params(self, params: OdometryParams) -> None:
        """New parameters before the first frame (the camera's readout, its depth model): every part's."""
        self._params = params
        for part in (self.front, self.map, self.tracker, self.backend, self.depth):
            part.params = params
        self.imu.enabled, self.imu.max_inertial_s = params.imu, params.max_inertial_s

    # -- the algorithm ----------------------------------------------------------------------------

    def prepare(self, frame: RgbdFrame) -> Any:
        """The work on the frame alone (its ORB features), for `track(frame, prepared)`: pure."""
        return self.front.prepare(frame)

    def track(self, frame: RgbdFrame, prepared: Any = None) -> TrackResult:
        """Estimate world_from_camera of `frame`; never raises for bad image content."""
        extracted = self.front.extract(frame, prepared, map_made=bool(self.map.keyframes))
        feats = self.front.features(frame, extracted, self.depth.offset)
        if not self.map.keyframes:
            res = self._initialise(frame, feats)
            if res.state == TrackingState.INIT:
                self.imu.observe(frame.stamp_ns, res.world_from_camera, continuous=False)
            return res
        if self.motion.last_pose is None:  # a saved map, the camera not found in it yet
            return self._find_in_saved(frame, feats, extracted)
        predicted, propagated = self.imu.predict(self.motion.predict(frame.stamp_ns), frame.stamp_ns)
        tracked, relocalised = self.tracker.locate(feats, predicted, frame.stamp_ns, self.imu.rotation_prior,
                                                   with_saved=self.saved.found_at >= 0)
        if tracked is not None and not relocalised and self.imu.rejects(tracked.camera_from_world, propagated):
            tracked = None  # a fit the IMU's motion cannot have made: the IMU's pose instead
        if tracked is None:
            if propagated is not None and self.imu.coasts(propagated):
                self.saved.carried += self.saved.found_at >= 0
                return self._coast(frame, propagated)
            self.motion.lost()  # the prediction keeps coming from the last tracked frame
            self.saved.lost += self.saved.found_at >= 0
            return TrackResult(frame.seq, frame.stamp_ns, predicted.copy(), TrackingState.LOST, False, -1, 0, 0)
        on_saved = 0
        if self.saved.found_at >= 0:
            on_saved = int(np.count_nonzero(tracked.map_idx < self.map.frozen_points))
            self.saved.localized += on_saved >= self.params.tracking.min_inliers
            self.saved.carried += on_saved < self.params.tracking.min_inliers
        pose = seen = invert(tracked.camera_from_world)
        kf_id, loop, deferred, map_moved_m, corrected = -1, None, False, 0.0, {}
        # A frame without enough depth adds no map points, so it must not replace the reference.
        if int(tracked.feats.has_depth.sum()) >= self.params.tracking.min_init_points and \
                self.map.need_keyframe(pose, tracked):
            kf_id, loop, deferred, map_moved_m, corrected, pose = self._keyframe(frame, pose, tracked)
        self.frames.add(frame.stamp_ns, self.map.keyframes[-1], pose)
        self.imu.observe(frame.stamp_ns, pose, continuous=not relocalised,
                         moved=None if pose is seen else pose @ invert(seen))
        self.motion.remember(frame.stamp_ns, pose, continuous=not relocalised)
        if self.params.localize:  # a temporary keyframe, and what the back end did to them: tracking's own
            kf_id, corrected = -1, {}
        return TrackResult(
            frame.seq, frame.stamp_ns, pose.copy(), TrackingState.OK, kf_id >= 0, kf_id, tracked.n_matches,
            tracked.n_inliers,
            corrected, loop, relocalised, tracked.residual, deferred, map_moved_m, self.depth.offset,
        )

    def _keyframe(self, frame: RgbdFrame, pose: np.ndarray, tracked: TrackedFrame
                  ) -> tuple[int, tuple[int, int] | None, bool, float, dict[int, np.ndarray], np.ndarray]:
        """The tracked frame becomes a keyframe: the back end's pending result (or not, deferred),
        the depth correction, its pose re-fitted if the map moved under it, its insertion and the
        next back-end job. Returns (id, loop, deferred, how far the map moved it, the keyframes
        corrected, its pose)."""
        feats = tracked.feats
        corrected: dict[int, np.ndarray] = {}
        loop = None
        deferred = self.backend.defer(frame.seq)
        moved_map = self.backend.pending is not None and not deferred
        before = pose
        if not deferred:
            corrected, loop, delta = self.backend.sync()
            if delta is not None:
                self.motion.move(delta)
                pose = delta @ pose
            # tracker.depth.correct_bias: every keyframe moves (not in a frozen saved map: it is the world)
            found = self.depth.found(self.map) if not self.map.frozen_keyframes else None
            if found is not None:
                s = self.depth.correct(self.map, found)
                self.frames.scale(s)
                self.backend.scale(s)
                self.motion.scale(s)
                corrected, pose, feats = self.keyframe_poses(), scaled(pose, s), recorrected(feats, found.inverse_offset)
                moved_map = True
        if moved_map:
            # the map moved under this frame: re-fit its pose to the moved points it matched
            sol = self.tracker.solve(feats, tracked.kp_idx, tracked.map_idx, invert(pose), use_ransac=False,
                                     rotation_prior=self.imu.rotation_prior)
            if sol is not None:
                pose = invert(sol[0])
        map_moved_m = float(np.linalg.norm(pose[:3, 3] - before[:3, 3]))
        kf_id = self._insert_keyframe(frame, pose, feats, tracked)
        if self.backend.pending is None:
            self.backend.submit(self.front.K)
        return kf_id, loop, deferred, map_moved_m, corrected, pose

    def _insert_keyframe(self, frame: RgbdFrame, pose: np.ndarray, feats: FrameFeatures, tracked: TrackedFrame) -> int:
        gyro = self.imu.keyframe_rotation(len(self.map.keyframes), frame.stamp_ns, self.map.keyframes)
        kf_id, new_kp = self.map.insert(frame.seq, pose, feats, tracked, gyro)
        if self.front.kp_state.size == len(feats):
            self.front.mark(new_kp, KeypointState.NEW)
        return kf_id

    def _initialise(self, frame: RgbdFrame, feats: FrameFeatures) -> TrackResult:
        """The first frame with enough depth is the first keyframe, at the world's origin."""
        pose = np.eye(4)
        with_depth = int(feats.has_depth.sum())
        if with_depth < self.params.tracking.min_init_points:
            self.init_best = max(self.init_best, with_depth)
            return TrackResult(frame.seq, frame.stamp_ns, pose, TrackingState.LOST, False, -1, 0, 0)
        empty = np.zeros(0, np.int64)
        kf_id = self._insert_keyframe(frame, pose, feats, TrackedFrame(np.eye(4), empty, empty, 0, 0, feats))
        self.frames.add_keyframe(frame.stamp_ns, kf_id)
        self.motion.remember(frame.stamp_ns, pose)
        return TrackResult(frame.seq, frame.stamp_ns, pose.copy(), TrackingState.INIT, True, kf_id, 0, 0)

    def _coast(self, frame: RgbdFrame, propagated: np.ndarray) -> TrackResult:
        """The frame vision could not place, at the IMU's pose (INERTIAL)."""
        self.frames.add(frame.stamp_ns, self.map.keyframes[-1], propagated)
        self.motion.coast(frame.stamp_ns, propagated)
        self.tracker.forget_seed()
        return TrackResult(frame.seq, frame.stamp_ns, propagated.copy(), TrackingState.INERTIAL, False, -1, 0, 0,
                           depth_inverse_offset=self.depth.offset)

    def finish(self) -> dict[int, np.ndarray]:
        """Wait for the back end and apply its last result; returns the keyframe poses it moved."""
        before = self.keyframe_poses()
        self._sync()
        if self.front.intrinsics is not None:
            self.backend.final_adjustment(self.front.K)
            self._sync()
        self.backend.close()
        after = self.keyframe_poses()
        if self.params.localize:  # only temporary keyframes moved (for the trajectory): nothing of the map
            return {}
        return {i: T for i, T in after.items() if not np.array_equal(T, before[i])}

    def _sync(self) -> None:
        _, _, delta = self.backend.sync()
        if delta is not None:
            self.motion.move(delta)

    # -- what it tells ----------------------------------------------------------------------------

    def keypoints(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (raw, as in the image) of the last frame's keypoints and their `KeypointState`s."""
        return self.front.pts, self.front.kp_state

    def local_map(self) -> np.ndarray:
        """World positions of the local map points the last frame was matched against."""
        ids = self.tracker.last_local[~self.map.points.bad[self.tracker.last_local]]
        return self.map.points.xyz[ids].copy()

    @property
    def n_keyframes(self) -> int:
        return len(self.map.keyframes)

    @property
    def n_map_points(self) -> int:
        return self.map.points.size

    def trajectory(self) -> tuple[list[int], list[np.ndarray]]:
        """Stamps and world_from_camera of every tracked frame, re-expressed through the current pose
        of the keyframe it was tracked against (so back-end corrections reach every frame)."""
        return self.frames.poses(self.map.keyframes)

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return {kf.id: kf.world_from_camera.copy() for kf in self.map.keyframes}

    @property
    def loops(self) -> list[tuple[int, int]]:
        """(new, old) keyframe ids of closed loops."""
        return self.backend.loops

    @property
    def rejected_jumps(self) -> int:
        """Tracked frames made LOST: a jump the motion cannot explain, on few inliers."""
        return self.tracker.rejected_jumps

    @property
    def worker(self) -> Worker | None:
        return self.backend.worker

    @property
    def worker_peak_rss_mb(self) -> float:
        return self.backend.worker_peak_rss_mb

    @property
    def worker_file_rss_mb(self) -> float:
        return self.backend.worker_file_rss_mb

    # -- the depth camera's bias ------------------------------------------------------------------

    @property
    def depth_offset(self) -> float:
        """The correction every reading takes now (1/m): the configured one plus what was found."""
        return self.depth.offset

    @property
    def depth_corrections(self) -> int:
        return self.depth.corrections

    @property
    def depth_model(self) -> DepthModel | None:
        return self.depth.model

    @depth_model.setter
    def depth_model(self, model: DepthModel | None) -> None:
        self.depth.model = model

    def depth_bias(self) -> DepthBias | None:
        """The depth camera's systematic error as the map has it (tracker/depth_bias.py), or None."""
        return self.depth.bias(self.map)

    # -- the IMU ----------------------------------------------------------------------------------

    def set_camera_from_imu(self, camera_from_imu: np.ndarray) -> None:
        """Where the IMU sits on the colour camera (4x4); before the first samples."""
        self.imu.set_camera_from_imu(camera_from_imu)

    def set_imu_noise(self, noise: ImuNoise) -> None:
        """The IMU's noise (the camera's properties); before the first samples (default: the D455's)."""
        self.imu.set_noise(noise)

    def add_imu(self, samples: ImuSamples) -> None:
        """IMU samples in time order, up to (at least) the next frame's stamp."""
        self.imu.add(samples)

    @property
    def imu_state(self) -> InertialState | None:
        return self.imu.state

    @property
    def imu_up(self) -> np.ndarray | None:
        return self.imu.up

    @property
    def inertial_frames(self) -> int:
        return self.imu.inertial_frames

    @property
    def imu_rejected(self) -> int:
        return self.imu.rejected

    # -- a saved map (SavedMapSearch) ---------------------------------------------------------------

    def adopt_map(self, saved: SavedMap) -> None:
        """Track in `saved` from the first frame on (before any frame)."""
        if self.map.keyframes:
            raise TrackingError("a saved map is taken before the first frame only")
        self.front.set_camera(saved.intrinsics)
        self.map.adopt(saved.points, saved.keyframes)
        self.backend.loop_edges = saved.loop_edges
        self.depth.offset = saved.depth_offset  # the same camera: its readings take the same correction
        self.saved = SavedMapSearch(keyframes=len(saved.keyframes))
        self.motion.last_pose = None

    def save_map(self, path: Path) -> None:
        """Write the map as it stands (after `finish`: the final bundle adjustment) to `path`."""
        if self.front.intrinsics is None:
            raise TrackingError("no map to save: no frame was tracked")
        keyframes, points, edges = self.map.keyframes, self.map.points, self.backend.loop_edges
        if self.params.localize:  # the saved map alone, as it came: the temporary keyframes are not the map
            n = self.map.frozen_keyframes
            keyframes, points = keyframes[:n], points.first(self.map.frozen_points)
            edges = [e for e in edges if e[0] < n and e[1] < n]
        save_map(path, intrinsics=self.front.intrinsics, keyframes=keyframes, points=points,
                 loop_edges=edges, depth_offset=self.depth.offset)

    @property
    def prior_keyframes(self) -> int:
        return self.saved.keyframes

    @property
    def prior_found_at(self) -> int:
        return self.saved.found_at

    @property
    def prior_misses(self) -> int:
        return self.saved.misses

    @property
    def prior_dropped(self) -> bool:
        return self.saved.dropped

    @property
    def prior_placed(self) -> int:
        return self.saved.placed

    def prior_counts(self) -> dict[str, int]:
        """Frames after the camera was found in the saved map: localized in it, carried by this
        session's own points (or the IMU), lost (SavedMapSearch)."""
        return {"localized": self.saved.localized, "carried": self.saved.carried, "lost": self.saved.lost}

    def _find_in_saved(self, frame: RgbdFrame, feats: FrameFeatures, extracted: Extracted) -> TrackResult:
        """A frame while the camera is not yet found in the saved map (see SavedMapSearch)."""
        search = self.saved
        if search.misses == 0 and search.sandbox is None:
            # made at the first frame, once the stream's camera has set the parameters
            vocabulary = self.map.index.vocabulary if self.map.index is not None else None
            search.sandbox = RgbdSlam(replace(self.params, localize=False), vocabulary=vocabulary)
            search.sandbox.depth.offset, search.sandbox.depth.model = self.depth.offset, self.depth.model
        own = search.sandbox.track(frame, (frame, extracted)) if search.sandbox is not None else None
        if own is not None and own.is_keyframe:
            search.held[own.keyframe_id] = frame.seq
        hold = own is not None and own.is_keyframe and not self.params.localize
        tried = search.misses % self.params.map_find_every == 0  # tracker.map_find_every
        tracked = self.tracker.find(feats, frame.stamp_ns) if tried else None
        if tracked is None:
            search.misses += 1
            if search.misses >= self.params.map_find_frames and not self.params.localize:
                return self._give_up(frame, own)  # localizing keeps looking: it makes no map of its own
            return TrackResult(frame.seq, frame.stamp_ns, np.eye(4), TrackingState.LOST, False, -1, 0, 0, hold=hold)
        pose = invert(tracked.camera_from_world)
        placed: dict[int, tuple[int, np.ndarray]] = {}
        if own is not None and own.state != TrackingState.LOST:
            placed = self._place_own(pose, own.world_from_camera)
        search.sandbox = None
        self.frames.drop_last_at(frame.stamp_ns)  # the map of its own had this frame too
        self.frames.add(frame.stamp_ns, self.map.keyframes[-1], pose)
        self.motion.remember(frame.stamp_ns, pose, continuous=False)
        search.found_at = frame.seq
        if self.params.localize:  # the map of its own placed as temporary keyframes: tracking's own
            placed = {}
        return TrackResult(frame.seq, frame.stamp_ns, pose.copy(), TrackingState.OK, False, -1, tracked.n_matches,
                           tracked.n_inliers, relocalised=True, residual=tracked.residual,
                           depth_inverse_offset=self.depth.offset, hold=hold, placed=placed)

    def _place_own(self, pose: np.ndarray, own_pose: np.ndarray) -> dict[int, tuple[int, np.ndarray]]:
        """The map of its own into the saved one, by the frame's pose in each (world_from_own = pose @
        own_pose^-1); its tracked frames join the trajectory. Returns the placed keyframes: id ->
        (frame seq, world_from_camera)."""
        own = self.saved.sandbox
        assert own is not None
        _, _, delta = own.backend.sync()  # its last back-end result in; the frame moves with it
        if delta is not None:
            own.motion.move(delta)
            own_pose = delta @ own_pose
        k0, _ = self.map.place(own.map, pose @ invert(own_pose))
        placed = {kf.id: (self.saved.held[kf.id - k0], kf.world_from_camera.copy()) for kf in own.map.keyframes}
        self.backend.place(own.backend, k0)
        self.frames.place(own.frames, k0)
        self.saved.placed = len(placed)
        return placed

    def _give_up(self, frame: RgbdFrame, own: TrackResult | None) -> TrackResult:
        """Not found in time: the map of its own becomes the map (the saved one is left as it was, it
        is not this session's world); its held keyframes go out, numbered from 0."""
        self.saved.dropped = True
        sandbox, self.saved.sandbox = self.saved.sandbox, None
        if own is None or sandbox is None:  # no map of its own to go on in: one from the next frame
            self.map.clear()
            self.backend.loop_edges = []
            self.frames.take(Trajectory())
            return TrackResult(frame.seq, frame.stamp_ns, np.eye(4), TrackingState.LOST, False, -1, 0, 0)
        self.map.take(sandbox.map)
        self.backend.take(sandbox.backend)
        self.frames.take(sandbox.frames)
        self.motion.take(sandbox.motion)
        self.tracker.take(sandbox.tracker)
        self.front.take(sandbox.front)
        self.depth.take(sandbox.depth)
        placed = {kf.id: (self.saved.held[kf.id], kf.world_from_camera.copy()) for kf in self.map.keyframes}
        return replace(own, hold=own.is_keyframe, placed=placed, is_keyframe=False, keyframe_id=-1)
