"""The tracker's front end: RGB-D odometry, ORB features tracked against a local map of keyframe points.

Per frame: extract ORB features spread over the image, read their depth, predict the pose with a
constant-velocity model, match projected local-map points around the prediction, estimate the
pose with `cv2.solvePnPRansac`, refine it with a robust (Huber) Gauss-Newton on reprojection and
inverse-depth residuals (tracker.pose), then match the local map again with the refined pose and
refine once more. Keyframes add new map points and fuse repeated depth readings of existing ones,
so drift is only accumulated when the camera leaves the area the local map covers. At every
keyframe the back end (tracker.backend: local BA, loop closing) runs on a snapshot of the map, in a
worker process or inline, and its result is applied at the next keyframe (live: a later one if busy).

The core sees only `RgbdFrame`s and one `OdometryParams` (no configuration tree, no I/O, no clock),
and is deterministic: the same frames give byte-identical poses in any process.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import cv2
import numpy as np

from octolog.kit.errors import TrackingError
from octolog.kit.geometry import Intrinsics, RgbdFrame, invert
from octolog.tracker.backend import BackendResult, run_backend
from octolog.tracker.backend_handoff import BackendHandoff
from octolog.tracker.config import OdometryParams, TrackerConfig
from octolog.tracker.depth_correction import DepthCorrection
from octolog.tracker.prior import PriorMap
from octolog.tracker.features import (
    FrameFeatures,
    OrbExtractor,
    Undistorter,
    backproject,
    grey_image,
    lookup_depth,
    match_brute_force,
    match_by_projection,
)
from octolog.tracker.interface import KeypointState, TrackingState, TrackResult
from octolog.tracker.keyframe_map import METRES_PER_RADIAN, Keyframe, MapPoints
from octolog.tracker.local_mapping import LocalMapping, TrackedFrame
from octolog.tracker.motion import MAX_PREDICTION_STEPS, MotionModel
from octolog.tracker.places import PLACE_MAX_HAMMING, PLACE_RATIO, BowIndex, relocalisation_guess
from octolog.tracker.pose import optimize_pose, so3_log, unroll_rolling_shutter, unsupported_jump
from octolog.tracker.vocab import Vocabulary
from octolog.tracker.worker import Worker

_RANSAC_SEED = 0x0C70
RANSAC_CONFIDENCE = 0.999  # PnP RANSAC stops once a consensus is this likely found (OpenCV's: 0.99)
# The second matching attempt widens the search window by this factor.
WIDE_SEARCH_FACTOR = 3.0
# A pose with this many times `min_inliers` inliers (and `confident_ratio` of its matches) is final;
# the previous frame's inliers seed the first match only if there are this many times `min_inliers`.
CONFIDENT_INLIER_FACTOR = 3


class RgbdSlam(LocalMapping, MotionModel, BackendHandoff, DepthCorrection, PriorMap):
    """RGB-D SLAM: frame-to-local-map tracking, keyframe insertion and the back end (loop closing, bundle
    adjustment). Call `track` once per frame, in time order, and `finish` at the end of the stream.

    `params` (default: `TrackerConfig()`'s) holds every tunable, by stage: features, depth gating,
    matching and pose fitting (`tracking`), keyframes, the local map, local and final bundle
    adjustment, loop closing, relocalisation. `params.readout_s` is the colour camera's
    rolling-shutter readout time (0: global shutter): keypoints are moved to mid-readout with the
    camera's velocity, from the motion model for the first pose, then from the previous frame to that
    pose for the second matching pass and the final fit (see `unroll_rolling_shutter`).
    With a `vocabulary`, loop and relocalisation candidates come from a bag-of-words index over it
    (the best `params.bow_candidates`), else every keyframe is a candidate. `background` runs the
    back end in a worker process (outputs are identical either way). One instance per camera
    stream; not thread-safe, but for `prepare`, which one other thread may call ahead of `track`.
    """

    def __init__(self, params: OdometryParams | None = None, *, vocabulary: Vocabulary | None = None,
                 background: bool | Worker = False, defer_backend: int = 0,
                 backend_deferred_at: frozenset[int] = frozenset()) -> None:
        self.params = params = params if params is not None else TrackerConfig().odometry_params()
        f = params.features
        make = partial(OrbExtractor, n_features=params.n_features, grid_cols=f.grid_cols, grid_rows=f.grid_rows,
                       fast_threshold=f.fast_threshold, min_fast_threshold=f.min_fast_threshold,
                       n_levels=f.n_levels, scale_factor=f.scale_factor)
        self._extractor, self._extractor_ahead = make(), make()  # the second for `prepare`'s thread
        self._bow = BowIndex(vocabulary) if vocabulary is not None else None
        # The back end (local BA, loop closing) for keyframe k starts when k is inserted and its result
        # is applied when keyframe k+1 is inserted (or at `finish`), or at a later one where
        # `_defer_backend` says (live; then on record): fixed points in the frame sequence, so a worker
        # process (`worker`, None inline; not a thread: the back end holds the GIL) changes no output.
        self.worker = background if isinstance(background, Worker) else Worker() if background else None
        self.defer_backend, self.backend_deferred_at, self._deferred_run = defer_backend, backend_deferred_at, 0
        self.worker_peak_rss_mb = self.worker_file_rss_mb = 0.0  # the worker's peak and file-backed MB (`finish`)
        self._pending: Worker | BackendResult | None = None
        self._loop_edges: list[tuple[int, int, np.ndarray]] = []
        self._last_loop_kf = -(10**9)
        self._loop_candidate: tuple[int, np.ndarray | None] = (-1, None)
        # per tracked frame: (stamp, reference keyframe id, reference_from_camera)
        self._frames: list[tuple[int, int, np.ndarray]] = []
        self._last_pts = np.zeros((0, 2))
        self._last_kp_state = np.zeros(0, np.uint8)
        self._last_local = np.zeros(0, np.int64)
        self.loops: list[tuple[int, int]] = []  # (new, old) keyframe ids of closed loops
        self.rejected_jumps = 0  # tracked frames made LOST: a jump the motion cannot explain, on few inliers
        self.depth_offset, self.depth_corrections = params.depth.inverse_offset, 0  # tracker.depth_correction

        self._intrinsics: Intrinsics | None = None
        self._undistort: Undistorter | None = None
        self._map = MapPoints()
        self._keyframes: list[Keyframe] = []
        self._kf_pos = np.zeros((0, 3))
        self._kf_axis = np.zeros((0, 3))
        self._last_pose: np.ndarray | None = None  # world_from_camera of the last tracked frame
        self._last_stamp = 0
        self._last_ok = False
        self._last_inlier_ids = np.zeros(0, np.int64)  # map points matched by the previous frame
        self._velocity: tuple[np.ndarray, np.ndarray, int] | None = None  # rotvec, trans, dt_ns

    # -- public ---------------------------------------------------------------------------------

    def keypoints(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (raw, as in the image) of the last frame's keypoints and their `KeypointState`s."""
        return self._last_pts, self._last_kp_state

    def local_map(self) -> np.ndarray:
        """World positions of the local map points the last frame was matched against."""
        ids = self._last_local[~self._map.bad[self._last_local]]
        return self._map.xyz[ids].copy()

    @property
    def n_keyframes(self) -> int:
        return len(self._keyframes)

    @property
    def n_map_points(self) -> int:
        return self._map.size

    def prepare(self, frame: RgbdFrame) -> Any:
        """The work on the frame alone (its ORB features), for `track(frame, prepared)`: pure."""
        try:
            return frame, self._extractor_ahead.extract(grey_image(frame))
        except TrackingError:
            return None  # `track` raises it, in its turn

    def track(self, frame: RgbdFrame, prepared: Any = None) -> TrackResult:
        """Estimate world_from_camera of `frame`; never raises for bad image content."""
        gray = self._check_frame(frame)
        extracted = prepared[1] if prepared is not None and prepared[0] is frame else self._extractor.extract(gray)
        feats = self._features(frame, extracted)
        if not self._keyframes:
            res = self._try_initialise(frame, feats)
            if res.state == TrackingState.INIT:
                self._imu_observe(frame.stamp_ns, res.world_from_camera, continuous=False)
            return res
        if self._last_pose is None:  # a saved map (tracker/prior.py), the camera not found in it yet
            return self._find_in_prior(frame, feats, extracted)
        predicted, propagated = self._imu_predict(self._predict(frame.stamp_ns), frame.stamp_ns)
        tracked, relocalised = self._locate(feats, predicted, frame.stamp_ns)
        if tracked is not None and not relocalised and self._imu_rejects(tracked.camera_from_world, propagated):
            tracked = None  # a fit the IMU's motion cannot have made: the IMU's pose instead
        if tracked is None:
            coasted = self._imu_coast(frame, propagated)
            if coasted is not None:
                return coasted
            self._last_ok = self._coasting = False  # the prediction keeps coming from the last tracked frame
            return TrackResult(frame.seq, frame.stamp_ns, predicted.copy(), TrackingState.LOST, False, -1, 0, 0)
        feats = tracked.feats
        pose = seen = invert(tracked.camera_from_world)
        kf_id, loop, deferred, map_moved_m = -1, None, False, 0.0
        corrected: dict[int, np.ndarray] = {}
        # A frame without enough depth adds no map points, so it must not replace the reference.
        if int(feats.has_depth.sum()) >= self.params.tracking.min_init_points and self._need_keyframe(pose, tracked):
            deferred = self._defer_backend(frame.seq)
            moved_map = self._pending is not None and not deferred
            before = pose
            if not deferred:
                corrected, loop, pose = self._sync_backend(pose)
                fixed = self._correct_depth(pose, feats)  # tracker.depth.correct_bias: every keyframe moves
                if fixed is not None:
                    (corrected, pose, feats), moved_map = fixed, True
            if moved_map:
                # the map moved under this frame: re-fit its pose to the moved points it matched
                sol = self._solve(feats, tracked.kp_idx, tracked.map_idx, invert(pose), use_ransac=False)
                if sol is not None:
                    pose = invert(sol[0])
            map_moved_m = float(np.linalg.norm(pose[:3, 3] - before[:3, 3]))
            kf_id = self._insert_keyframe(frame.seq, frame.stamp_ns, pose, feats, tracked)
            if self._pending is None:
                self._submit_backend()
        ref = self._keyframes[-1]
        self._frames.append((frame.stamp_ns, ref.id, invert(ref.world_from_camera) @ pose))
        self._imu_observe(frame.stamp_ns, pose, continuous=not relocalised,
                          moved=None if pose is seen else pose @ invert(seen))
        self._remember(frame.stamp_ns, pose, continuous=not relocalised)
        return TrackResult(
            frame.seq, frame.stamp_ns, pose.copy(), TrackingState.OK, kf_id >= 0, kf_id, tracked.n_matches,
            tracked.n_inliers,
            corrected, loop, relocalised, tracked.residual, deferred, map_moved_m, self.depth_offset,
        )

    def _locate(self, feats: FrameFeatures, predicted: np.ndarray, stamp_ns: int) -> tuple[TrackedFrame | None, bool]:
        """The frame against the map from the prediction, else by place recognition; None when it
        cannot be placed with the evidence its case asks for; and whether it was found again."""
        by_place = False
        try:
            tracked = self._track_against_map(feats, predicted, stamp_ns)
            if tracked is None and self.params.relocalise:
                assert self._undistort is not None
                guess = relocalisation_guess(feats, self._keyframes, self._bow, self.params, self._undistort.K)
                if guess is not None:
                    tracked = self._track_against_map(feats, guess, stamp_ns)
                    by_place = tracked is not None
        except (cv2.error, np.linalg.LinAlgError):
            # Degenerate geometry inside OpenCV or a singular system: this frame is untrackable,
            # the stream is not broken.
            tracked = None
        # after a tracked frame, or a few LOST frames after one, the motion model's prediction is
        # meaningful: the pose is judged as a step from it
        continuous = self._last_ok or self._coasting or (self._velocity is not None and
                                       stamp_ns - self._last_stamp <= MAX_PREDICTION_STEPS * self._velocity[2])
        if tracked is not None and not by_place and self._velocity is not None and continuous and \
                unsupported_jump(self.params.tracking, predicted, invert(tracked.camera_from_world), tracked.n_inliers,
                                 stamp_ns - self._last_stamp):
            self.rejected_jumps += 1
            tracked = None
        # found again, after a longer LOST stretch or by place recognition (the step is unknown): only on
        # the evidence ORB-SLAM asks of a relocalisation, and announced (TrackingStatus.relocalised)
        relocalised = tracked is not None and (by_place or not continuous)
        if tracked is not None and relocalised and tracked.n_inliers < self.params.tracking.relocalise_min_inliers:
            tracked = None
        return tracked, relocalised

    def trajectory(self) -> tuple[list[int], list[np.ndarray]]:
        """Stamps and world_from_camera of every tracked frame, re-expressed through the current pose
        of the keyframe it was tracked against (so back-end corrections reach every frame)."""
        kfs = self._keyframes
        return [s for s, _, _ in self._frames], [kfs[k].world_from_camera @ T for _, k, T in self._frames]

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return {kf.id: kf.world_from_camera.copy() for kf in self._keyframes}

    def finish(self) -> dict[int, np.ndarray]:
        """Wait for the back end and apply its last result; returns the keyframe poses it moved."""
        before = self.keyframe_poses()
        self._sync_backend(np.eye(4))
        if self.params.global_ba_keyframes > 0 and self.params.local_ba and len(self._keyframes) >= 2 and \
                not self.params.localize:
            # a last bundle adjustment, as ORB-SLAM runs after a loop, so what is written out has the
            # whole map's support: every keyframe (the first fixed) up to `global_ba_keyframes`, else
            # the newest that many, bounded in time and memory (in the worker when there is one)
            window_n = min(len(self._keyframes), self.params.global_ba_keyframes)
            job = self._backend_job(window_n=window_n, max_points=None, loop_closing=False,
                                    iterations=self.params.bundle_adjustment.global_iterations)
            self._pending = self.worker.submit(job) if self.worker else run_backend(job)
            self._sync_backend(np.eye(4))
        if self.worker is not None:
            self.worker.close()
            self.worker_peak_rss_mb, self.worker_file_rss_mb = self.worker.peak_rss_mb, self.worker.file_rss_mb
            self.worker = None
        after = self.keyframe_poses()
        return {i: T for i, T in after.items() if not np.array_equal(T, before[i])}

    # -- input ----------------------------------------------------------------------------------

    def _check_frame(self, frame: RgbdFrame) -> np.ndarray:
        """Grey image of the frame; TrackingError when the frame cannot match its intrinsics."""
        gray = grey_image(frame)
        intr = frame.intrinsics
        if intr != self._intrinsics:
            if self._intrinsics is not None and self._keyframes:
                raise TrackingError(f"frame {frame.seq}: intrinsics {intr} differ from the map's "
                                    f"{self._intrinsics}: another camera or resolution")
            self._intrinsics = intr
            self._undistort = Undistorter(intr)
        return gray

    def _unroll(self, feats: FrameFeatures, step: tuple[np.ndarray, np.ndarray, int]) -> FrameFeatures:
        assert self._undistort is not None and self._intrinsics is not None
        return unroll_rolling_shutter(feats, self._last_pts[:, 1], self._intrinsics.height, self._undistort.K,
                                      self.params.readout_s, step)

    def _features(self, frame: RgbdFrame, extracted: tuple[np.ndarray, np.ndarray, np.ndarray]) -> FrameFeatures:
        assert self._undistort is not None
        pts, octave, desc = extracted
        d = self.params.depth
        z = lookup_depth(frame.depth, frame.depth_scale_m, pts, min_depth_m=d.min_m, max_depth_m=d.max_m,
                         max_spread=d.edge_spread)
        if self.depth_offset:
            z = z / (1.0 - self.depth_offset * z)  # 0 stays 0
        uv = self._undistort(pts)
        self._last_pts = pts
        self._last_kp_state = np.zeros(len(pts), np.uint8)
        return FrameFeatures(uv=uv, octave=octave, desc=desc, z=z, xyz=backproject(uv, z, self._undistort.K))

    # -- initialisation -------------------------------------------------------------------------

    def _try_initialise(self, frame: RgbdFrame, feats: FrameFeatures) -> TrackResult:
        pose = np.eye(4)
        if int(feats.has_depth.sum()) < self.params.tracking.min_init_points:
            return TrackResult(frame.seq, frame.stamp_ns, pose, TrackingState.LOST, False, -1, 0, 0)
        empty = np.zeros(0, np.int64)
        tracked = TrackedFrame(np.eye(4), empty, empty, 0, 0, feats)
        kf_id = self._insert_keyframe(frame.seq, frame.stamp_ns, pose, feats, tracked)
        self._frames.append((frame.stamp_ns, kf_id, np.eye(4)))
        self._remember(frame.stamp_ns, pose)
        return TrackResult(frame.seq, frame.stamp_ns, pose.copy(), TrackingState.INIT, True, kf_id, 0, 0)

    # -- tracking -------------------------------------------------------------------------------

    def _local_keyframes(self, world_from_camera: np.ndarray, count: int) -> np.ndarray:
        """Sorted indices of the `count` keyframes nearest to a pose, always with the newest."""
        n_kf = len(self._keyframes)
        axis = world_from_camera[:3, 2]
        dist = np.linalg.norm(self._kf_pos - world_from_camera[:3, 3], axis=1)
        angle = np.arccos(np.clip(self._kf_axis @ axis, -1.0, 1.0))
        score = dist + METRES_PER_RADIAN * angle
        score[max(0, n_kf - self.params.local_map.n_recent_keyframes) :] = -1.0
        return np.sort(np.lexsort((np.arange(n_kf), score))[:count])

    def _local_points(self, world_from_camera: np.ndarray) -> np.ndarray:
        """Sorted ids of good map points seen by the keyframes nearest to a pose plus the newest."""
        kfs = self._local_keyframes(world_from_camera, self.params.local_map.n_keyframes)
        ids = np.unique(np.concatenate([self._keyframes[i].point_ids for i in kfs]))
        return ids[~self._map.bad[ids]]

    def _project(self, ids: np.ndarray, camera_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projected pixels of map points and the mask of those in front of and inside the image."""
        assert self._intrinsics is not None
        intr = self._intrinsics
        p = self._map.xyz[ids] @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        z = p[:, 2]
        front = z > self.params.depth.min_m * 0.5
        zs = np.where(front, z, 1.0)
        uv = np.empty((ids.size, 2))
        uv[:, 0] = intr.fx * p[:, 0] / zs + intr.cx
        uv[:, 1] = intr.fy * p[:, 1] / zs + intr.cy
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
        return uv, inside

    def _guided(
        self, feats: FrameFeatures, ids: np.ndarray, camera_from_world: np.ndarray, radius: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keypoint idx, map id) matches of local points projected with a pose; also visible ids."""
        uv, inside = self._project(ids, camera_from_world)
        vis = ids[inside]
        mi, ki, _ = match_by_projection(
            uv[inside],
            self._map.desc[vis],
            feats.uv,
            feats.desc,
            radius=radius,
            max_distance=self.params.tracking.max_hamming,
            ratio=self.params.tracking.match_ratio,
        )
        return ki, vis[mi], vis

    def _confident(self, n_inliers: int, n_matches: int) -> bool:
        """Whether a pose has so many consistent matches that escalating cannot beat it."""
        t = self.params.tracking
        return n_inliers >= CONFIDENT_INLIER_FACTOR * t.min_inliers and n_inliers >= t.confident_ratio * n_matches

    def _solve(
        self, feats: FrameFeatures, kp_idx: np.ndarray, map_idx: np.ndarray, guess_cw: np.ndarray, use_ransac: bool,
        rounds: int = 3,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Pose (camera_from_world) and inlier mask from matches, or None when unreliable."""
        assert self._undistort is not None
        K, t = self._undistort.K, self.params.tracking
        if kp_idx.size < t.min_inliers:
            return None
        pts_w = self._map.xyz[map_idx]
        uv = feats.uv[kp_idx]
        init_inl = None
        guess = guess_cw
        if use_ransac:
            cv2.setRNGSeed(_RANSAC_SEED)
            try:
                ok, rvec, tvec, inl = cv2.solvePnPRansac(
                    pts_w.reshape(-1, 1, 3), uv.reshape(-1, 1, 2), K, None, iterationsCount=t.ransac_iterations,
                    reprojectionError=t.ransac_reproj_px, confidence=RANSAC_CONFIDENCE, flags=cv2.SOLVEPNP_EPNP)
            except cv2.error:
                return None
            if not ok or inl is None or inl.size < t.min_inliers:
                return None
            guess = np.eye(4)
            guess[:3, :3] = cv2.Rodrigues(rvec)[0]
            guess[:3, 3] = tvec.ravel()
            init_inl = np.zeros(kp_idx.size, dtype=bool)
            init_inl[inl.ravel()] = True
        inv_sigma = self.params.features.scale_factor ** (-feats.octave[kp_idx].astype(np.float64))
        T, inl_mask = optimize_pose(guess, pts_w, uv, inv_sigma, feats.z[kp_idx], K, inv_depth_sigma=t.inv_depth_sigma,
                                    inliers=init_inl, rounds=rounds, rotation_prior=self._rotation_prior)
        if int(inl_mask.sum()) < t.min_inliers or not np.all(np.isfinite(T)):
            return None
        return T, inl_mask

    def _track_against_map(self, raw: FrameFeatures, predicted_wc: np.ndarray, stamp_ns: int) -> TrackedFrame | None:
        """Match and estimate the pose; None when the frame cannot be tracked.

        With a rolling shutter the keypoints are moved to mid-readout twice: with the motion
        model's velocity for the first pose, then with the velocity from the previous frame to that
        pose (half a frame old instead of one and a half) for the second matching pass and the pose
        that is kept."""
        if len(raw) < self.params.tracking.min_inliers:
            return None
        rolling = self.params.readout_s > 0.0 and self._last_ok
        feats = self._unroll(raw, self._velocity) if rolling and self._velocity is not None else raw
        guess_cw = invert(predicted_wc)
        local = self._local_points(predicted_wc)

        best, attempt = self._first_pass(feats, local, guess_cw)
        if best is None:
            return None
        first = (best[0], best[1])
        ki, mi = best[2], best[3]
        if attempt > 0:
            local = self._local_points(invert(best[0]))
        T_cw, _ = first

        # Second pass: with a good pose, all local points can be matched in a tight window.
        feats2 = feats
        if rolling:
            assert self._last_pose is not None
            step = invert(self._last_pose) @ invert(T_cw)
            feats2 = self._unroll(raw, (so3_log(step[:3, :3]), step[:3, 3].copy(), stamp_ns - self._last_stamp))
        ki2, mi2, visible = self._guided(feats2, local, T_cw, self.params.tracking.refine_radius_px)
        second = self._solve(feats2, ki2, mi2, T_cw, use_ransac=False)
        if second is not None and int(second[1].sum()) >= int(first[1].sum()) // 2:
            T_cw, inl = second
            ki, mi = ki2, mi2
            feats = feats2
        else:
            inl = first[1]
        self._map.n_visible[visible] += 1
        self._map.n_found[mi[inl]] += 1
        self._last_inlier_ids = np.sort(mi[inl])
        self._last_kp_state[ki] = KeypointState.OUTLIER
        self._last_kp_state[ki[inl]] = KeypointState.TRACKED
        self._last_local = local
        ki, mi = ki[inl], mi[inl]
        uv, _ = self._project(mi, T_cw)
        level_scale = self.params.features.scale_factor ** -feats.octave[ki].astype(np.float64)
        scaled = (uv - feats.uv[ki]) * level_scale[:, None]
        residual = float(np.sqrt(np.mean(np.sum(scaled * scaled, axis=1)))) if ki.size else float("nan")
        return TrackedFrame(T_cw, ki, mi, int(inl.size), int(inl.sum()), feats, residual)

    def _first_pass(self, feats: FrameFeatures, local: np.ndarray, guess_cw: np.ndarray
                    ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None, int]:
        """The first pose: matches and a robust fit, escalating while the answer is weak; the best
        (pose, inliers, keypoint ids, map ids) or None, and the attempt it stopped at."""
        # Escalate only while the answer is weak: a tight window around the prediction, wide ones, then
        # descriptor matching against the map around the last tracked pose (after LOST or a jolt the
        # prediction is useless, and that is where tracking resumes). Best inlier count wins.
        best: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None  # T, inl, ki, mi
        # The windows search the points the previous frame matched (the seed) first: visible, distinctive,
        # a third to a sixth of the local map, enough for a seed pose; fast motion outruns the tight window
        # (then a wide one over the seed, then over all). The second pass below matches the whole local map.
        seed = self._last_inlier_ids if self._last_ok else np.zeros(0, np.int64)
        if seed.size < CONFIDENT_INLIER_FACTOR * self.params.tracking.min_inliers:
            seed = local
        plan = [(seed, 1.0), (seed, WIDE_SEARCH_FACTOR)] + ([(local, WIDE_SEARCH_FACTOR)] if seed is not local else [])
        for attempt in range(len(plan) + 1):
            if attempt < len(plan):
                ids, factor = plan[attempt]
                ki, mi, _ = self._guided(feats, ids, guess_cw, self.params.tracking.search_radius_px * factor)
            else:
                around = self._local_points(self._last_pose if self._last_pose is not None else invert(guess_cw))
                q, tr, _ = match_brute_force(feats.desc, self._map.desc[around], max_distance=PLACE_MAX_HAMMING,
                                            ratio=PLACE_RATIO)
                ki, mi = q, around[tr]
            # Behind a tracked frame the motion model's pose is a good start: a robust fit from it
            # needs no RANSAC (as ORB-SLAM's motion-model step); escalation brings RANSAC back.
            # This pose only seeds the tight second matching pass: two rounds suffice.
            trusted = attempt == 0 and self._last_ok and self._velocity is not None
            sol = self._solve(feats, ki, mi, guess_cw, use_ransac=not trusted, rounds=2)
            if sol is not None and (best is None or int(sol[1].sum()) > int(best[1].sum())):
                best = (sol[0], sol[1], ki, mi)
            if best is not None and self._confident(int(best[1].sum()), best[2].size):
                break
        return best, attempt
