"""The SLAM core's pose fit: a frame's features matched to the local map's points around a
predicted pose and the pose estimated from them (`cv2.solvePnPRansac`, then a robust Gauss-Newton
on reprojection and inverse-depth residuals, tracker/pose.py), then matched again with the refined
pose and refined once more; when the prediction fails, place recognition; a pose the motion cannot
explain on few inliers, or a relocalisation on too few, is refused.

`MapTracker` owns what one fit leaves for the next: the points the last frame matched (the next
frame's seed) and the local points it was matched against. It reads the map, the camera and the
motion model, and counts each fit's visible and found points in the map's statistics.
"""

from __future__ import annotations

import cv2
import numpy as np

from octolog.kit.geometry import invert
from octolog.tracker.config import OdometryParams
from octolog.tracker.features import FrameFeatures, match_brute_force, match_by_projection
from octolog.tracker.front_end import FrontEnd
from octolog.tracker.interface import KeypointState
from octolog.tracker.local_map import LocalMap, TrackedFrame
from octolog.tracker.motion import MotionModel
from octolog.tracker.places import PLACE_MAX_HAMMING, PLACE_RATIO, relocalisation_guess
from octolog.tracker.pose import optimize_pose, so3_log, unsupported_jump

_RANSAC_SEED = 0x0C70
RANSAC_CONFIDENCE = 0.999  # PnP RANSAC stops once a consensus is this likely found (OpenCV's: 0.99)
# The second matching attempt widens the search window by this factor.
WIDE_SEARCH_FACTOR = 3.0
# A pose with this many times `min_inliers` inliers (and `confident_ratio` of its matches) is final;
# the previous frame's inliers seed the first match only if there are this many times `min_inliers`.
CONFIDENT_INLIER_FACTOR = 3
CHI2_POSE_99 = 16.81  # chi-square, 6 degrees of freedom (a pose), 99 %

RotationPrior = tuple[np.ndarray, float]


def point_sigmas(weight: np.ndarray, points_w: np.ndarray, camera_from_world: np.ndarray, K: np.ndarray,
                 inv_sigma_px: np.ndarray, inv_depth_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Residual scales (1 / sigma: pixels, inverse depth) that carry each map point's own error.

    A point fused from readings at ranges z_i (`MapPoints.weight` = sum z_i^-4) is known to
    sigma_p = inv_depth_sigma / sqrt(weight) metres (the depth error grows with z^2). Seen from
    range z now, that is f sigma_p / z pixels and sigma_p / z^2 in inverse depth, added in
    quadrature to the keypoint's own sigmas. A saved map's wall seen from 3 m, localized in from
    1 m, weighs what it is worth against the points seen from close by."""
    sigma_p = inv_depth_sigma / np.sqrt(np.maximum(weight, 1e-12))
    z = np.maximum(points_w @ camera_from_world[2, :3] + camera_from_world[2, 3], 1e-3)
    px = K[0, 0] * sigma_p / z
    inv_px = 1.0 / np.sqrt(inv_sigma_px ** -2 + px * px)
    inv_d = 1.0 / np.sqrt(inv_depth_sigma ** 2 + (sigma_p / (z * z)) ** 2)
    return inv_px, inv_d


class MapTracker:
    """Frame-to-local-map pose estimation over `local_map`, with `front`'s camera and `motion`'s prediction."""

    def __init__(self, params: OdometryParams, front: FrontEnd, local_map: LocalMap, motion: MotionModel) -> None:
        self.params = params
        self._front, self._map, self._motion = front, local_map, motion
        self.last_inlier_ids = np.zeros(0, np.int64)  # map points matched by the previous frame
        self.last_local = np.zeros(0, np.int64)  # the local map points the last frame was matched against
        self.rejected_jumps = 0  # tracked frames made LOST: a jump the motion cannot explain, on few inliers

    def locate(self, feats: FrameFeatures, predicted: np.ndarray, stamp_ns: int,
               rotation_prior: RotationPrior | None = None,
               with_saved: bool = False) -> tuple[TrackedFrame | None, bool]:
        """The frame against the map from the prediction, else by place recognition; None when it
        cannot be placed with the evidence its case asks for; and whether it was found again.
        `with_saved` (a saved map the camera was found in): the local map's points and the saved
        map's in view, these weighed by their own error (`track`)."""
        by_place = False
        try:
            tracked = self.track(feats, predicted, stamp_ns, rotation_prior, with_saved)
            if tracked is None and self.params.relocalise:
                guess = relocalisation_guess(feats, self._map.keyframes, self._map.index, self.params, self._front.K)
                if guess is not None:
                    tracked = self.track(feats, guess, stamp_ns, rotation_prior)
                    by_place = tracked is not None
        except (cv2.error, np.linalg.LinAlgError):
            # Degenerate geometry inside OpenCV or a singular system: this frame is untrackable,
            # the stream is not broken.
            tracked = None
        motion = self._motion
        continuous = motion.continuous(stamp_ns)
        if tracked is not None and not by_place and motion.velocity is not None and continuous and \
                unsupported_jump(self.params.tracking, predicted, invert(tracked.camera_from_world), tracked.n_inliers,
                                 stamp_ns - motion.last_stamp):
            self.rejected_jumps += 1
            tracked = None
        # found again, after a longer LOST stretch or by place recognition (the step is unknown): only on
        # the evidence ORB-SLAM asks of a relocalisation, and announced (TrackingStatus.relocalised)
        relocalised = tracked is not None and (by_place or not continuous)
        if tracked is not None and relocalised and tracked.n_inliers < self.params.tracking.relocalise_min_inliers:
            tracked = None
        return tracked, relocalised

    def find(self, feats: FrameFeatures, stamp_ns: int) -> TrackedFrame | None:
        """The frame by place recognition alone (a camera not yet found in a saved map), on the
        evidence a relocalisation needs; None when not found."""
        guess = relocalisation_guess(feats, self._map.keyframes, self._map.index, self.params, self._front.K)
        tracked = None
        if guess is not None:
            try:
                tracked = self.track(feats, guess, stamp_ns)
            except (cv2.error, np.linalg.LinAlgError):
                tracked = None
        if tracked is None or tracked.n_inliers < self.params.tracking.relocalise_min_inliers:
            return None
        return tracked

    def track(self, raw: FrameFeatures, predicted_wc: np.ndarray, stamp_ns: int,
              rotation_prior: RotationPrior | None = None, with_saved: bool = False) -> TrackedFrame | None:
        """Match and estimate the pose; None when the frame cannot be tracked.

        With a rolling shutter the keypoints are moved to mid-readout twice: with the motion
        model's velocity for the first pose, then with the velocity from the previous frame to that
        pose (half a frame old instead of one and a half) for the second matching pass and the pose
        that is kept."""
        if len(raw) < self.params.tracking.min_inliers:
            return None
        motion = self._motion
        rolling = self.params.readout_s > 0.0 and motion.tracked
        feats = self._front.unroll(raw, motion.velocity) if rolling and motion.velocity is not None else raw
        guess_cw = invert(predicted_wc)
        local = self._local(predicted_wc, with_saved)

        best, attempt = self._first_pass(feats, local, guess_cw, rotation_prior, with_saved)
        if best is None:
            return None
        first = (best[0], best[1])
        ki, mi = best[2], best[3]
        if attempt > 0:
            local = self._local(invert(best[0]), with_saved)
        T_cw, _ = first

        # Second pass: with a good pose, all local points can be matched in a tight window.
        feats2 = feats
        if rolling:
            assert motion.last_pose is not None
            step = invert(motion.last_pose) @ invert(T_cw)
            feats2 = self._front.unroll(raw, (so3_log(step[:3, :3]), step[:3, 3].copy(), stamp_ns - motion.last_stamp))
        ki2, mi2, visible = self._guided(feats2, local, T_cw, self.params.tracking.refine_radius_px)
        second = self._established_first(feats2, ki2, mi2, T_cw, rotation_prior, with_saved)
        if second is not None and int(second[1].sum()) >= int(first[1].sum()) // 2:
            T_cw, inl = second
            ki, mi = ki2, mi2
            feats = feats2
        else:
            inl = first[1]
        points = self._map.points
        points.n_visible[visible] += 1
        points.n_found[mi[inl]] += 1
        self.last_inlier_ids = np.sort(mi[inl])
        self._front.mark(ki, KeypointState.OUTLIER)
        self._front.mark(ki[inl], KeypointState.TRACKED)
        self.last_local = local
        ki, mi = ki[inl], mi[inl]
        assert self._front.intrinsics is not None
        uv, _ = self._map.project(mi, T_cw, self._front.intrinsics)
        level_scale = self.params.features.scale_factor ** -feats.octave[ki].astype(np.float64)
        scaled = (uv - feats.uv[ki]) * level_scale[:, None]
        residual = float(np.sqrt(np.mean(np.sum(scaled * scaled, axis=1)))) if ki.size else float("nan")
        return TrackedFrame(T_cw, ki, mi, int(inl.size), int(inl.sum()), feats, residual)

    def _established_first(self, feats: FrameFeatures, ki: np.ndarray, mi: np.ndarray, guess_cw: np.ndarray,
                           rotation_prior: RotationPrior | None, with_saved: bool
                           ) -> tuple[np.ndarray, np.ndarray] | None:
        """The second pass's pose: fitted to every match, unless the young points (no keyframe has
        seen them again yet) pull it away from the established ones (seen from two keyframes or
        more). A keyframe makes points on whatever it sees, a person walking by too; for the next
        few frames those points move with the person, all together, and a fit to every match
        follows them. Then the two fits' camera centres are more than `tracking.young_pull_m` apart,
        and the established points' squared reprojection error under the fit to every match exceeds
        that under their own fit by more than chance allows for a 6-DoF pose (chi-square, 99 %, in
        units of their own scatter), and the pose is theirs; the young points that agree with it count as its inliers
        but do not pull it. Where few points are established, every match."""
        t = self.params.tracking
        every = self.solve(feats, ki, mi, guess_cw, use_ransac=False, rotation_prior=rotation_prior,
                           weigh_points=with_saved)
        young = self._map.points.n_obs[mi] <= 1
        if every is None or not t.young_pull_m or not young.any() or int((~young).sum()) < CONFIDENT_INLIER_FACTOR * t.min_inliers:
            return every
        old = self.solve(feats, ki[~young], mi[~young], every[0], use_ransac=False, rotation_prior=rotation_prior,
                         weigh_points=with_saved)
        if old is None:
            return every
        settled = np.flatnonzero(~young)[old[1]]
        shift = float(np.linalg.norm(invert(every[0])[:3, 3] - invert(old[0])[:3, 3]))
        if shift <= t.young_pull_m:
            return every
        own = self._chi2(feats, ki[settled], mi[settled], old[0])
        variance = own / max(settled.size - 6, 1)  # the established points' own scatter, per point
        if self._chi2(feats, ki[settled], mi[settled], every[0]) - own <= CHI2_POSE_99 * variance:
            return every
        inl = np.zeros(ki.size, bool)
        inl[settled] = True
        yk, ym = ki[young], mi[young]
        assert self._front.intrinsics is not None
        uv, _ = self._map.project(ym, old[0], self._front.intrinsics)
        level = self.params.features.scale_factor ** feats.octave[yk].astype(np.float64)
        inl[np.flatnonzero(young)] = np.linalg.norm(uv - feats.uv[yk], axis=1) <= t.refine_radius_px * level
        return old[0], inl

    def _chi2(self, feats: FrameFeatures, ki: np.ndarray, mi: np.ndarray, camera_from_world: np.ndarray) -> float:
        """Sum of the squared reprojection errors of matches under a pose, in their keypoints' sigmas."""
        assert self._front.intrinsics is not None
        uv, _ = self._map.project(mi, camera_from_world, self._front.intrinsics)
        inv_sigma = self.params.features.scale_factor ** (-feats.octave[ki].astype(np.float64))
        return float(np.sum(np.sum((uv - feats.uv[ki]) ** 2, axis=1) * inv_sigma ** 2))

    def _local(self, world_from_camera: np.ndarray, with_saved: bool) -> np.ndarray:
        """The points a pose is matched against: the local map's, and the saved map's in view (by
        view, not by distance: a session walking the other way stands where the saved keyframes
        looked elsewhere)."""
        local = self._map.local_points(world_from_camera)
        if with_saved:
            assert self._front.intrinsics is not None
            local = np.union1d(local, self._map.saved_points_in_view(world_from_camera, self._front.intrinsics))
        return local

    def solve(
        self, feats: FrameFeatures, kp_idx: np.ndarray, map_idx: np.ndarray, guess_cw: np.ndarray, use_ransac: bool,
        rounds: int = 3, rotation_prior: RotationPrior | None = None, weigh_points: bool = False,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Pose (camera_from_world) and inlier mask from matches, or None when unreliable.
        `weigh_points`: a saved map's points (`LocalMap.frozen_points`) carry their own error
        (`point_sigmas`) in their residuals' sigmas."""
        K, t = self._front.K, self.params.tracking
        if kp_idx.size < t.min_inliers:
            return None
        pts_w = self._map.points.xyz[map_idx]
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
        inv_depth_sigma: float | np.ndarray = t.inv_depth_sigma
        if weigh_points and np.any(saved := map_idx < self._map.frozen_points):
            inv_sigma, inv_depth_sigma = inv_sigma.copy(), np.full(map_idx.size, t.inv_depth_sigma)
            inv_sigma[saved], inv_depth_sigma[saved] = point_sigmas(
                self._map.points.weight[map_idx[saved]], pts_w[saved], guess, K, inv_sigma[saved], t.inv_depth_sigma)
        T, inl_mask = optimize_pose(guess, pts_w, uv, inv_sigma, feats.z[kp_idx], K, inv_depth_sigma=inv_depth_sigma,
                                    inliers=init_inl, rounds=rounds, rotation_prior=rotation_prior)
        if int(inl_mask.sum()) < t.min_inliers or not np.all(np.isfinite(T)):
            return None
        return T, inl_mask

    def forget_seed(self) -> None:
        """The next frame starts from no matched points (the last pose was not vision's)."""
        self.last_inlier_ids = np.zeros(0, np.int64)

    def take(self, other: MapTracker) -> None:
        """Another tracker's seed and local points (a map of its own becomes the map)."""
        self.last_inlier_ids, self.last_local = other.last_inlier_ids, other.last_local

    # -- matching ----------------------------------------------------------------------------------

    def _guided(
        self, feats: FrameFeatures, ids: np.ndarray, camera_from_world: np.ndarray, radius: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keypoint idx, map id) matches of local points projected with a pose; also visible ids."""
        assert self._front.intrinsics is not None
        uv, inside = self._map.project(ids, camera_from_world, self._front.intrinsics)
        vis = ids[inside]
        mi, ki, _ = match_by_projection(
            uv[inside],
            self._map.points.desc[vis],
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

    def _first_pass(self, feats: FrameFeatures, local: np.ndarray, guess_cw: np.ndarray,
                    rotation_prior: RotationPrior | None, with_saved: bool = False
                    ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None, int]:
        """The first pose: matches and a robust fit, escalating while the answer is weak; the best
        (pose, inliers, keypoint ids, map ids) or None, and the attempt it stopped at; `with_saved`:
        the saved map's points weighed by their own error."""
        # Escalate only while the answer is weak: a tight window around the prediction, wide ones, then
        # descriptor matching against the map around the last tracked pose (after LOST or a jolt the
        # prediction is useless, and that is where tracking resumes). Best inlier count wins.
        best: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None  # T, inl, ki, mi
        # The windows search the points the previous frame matched (the seed) first: visible, distinctive,
        # a third to a sixth of the local map, enough for a seed pose; fast motion outruns the tight window
        # (then a wide one over the seed, then over all). The second pass below matches the whole local map.
        motion = self._motion
        seed = self.last_inlier_ids if motion.tracked else np.zeros(0, np.int64)
        if seed.size < CONFIDENT_INLIER_FACTOR * self.params.tracking.min_inliers:
            seed = local
        plan = [(seed, 1.0), (seed, WIDE_SEARCH_FACTOR)] + ([(local, WIDE_SEARCH_FACTOR)] if seed is not local else [])
        for attempt in range(len(plan) + 1):
            if attempt < len(plan):
                ids, factor = plan[attempt]
                ki, mi, _ = self._guided(feats, ids, guess_cw, self.params.tracking.search_radius_px * factor)
            else:
                around = self._map.local_points(motion.last_pose if motion.last_pose is not None else invert(guess_cw))
                q, tr, _ = match_brute_force(feats.desc, self._map.points.desc[around], max_distance=PLACE_MAX_HAMMING,
                                            ratio=PLACE_RATIO)
                ki, mi = q, around[tr]
            # Behind a tracked frame the motion model's pose is a good start: a robust fit from it
            # needs no RANSAC (as ORB-SLAM's motion-model step); escalation brings RANSAC back.
            # This pose only seeds the tight second matching pass: two rounds suffice.
            trusted = attempt == 0 and motion.tracked and motion.velocity is not None
            sol = self.solve(feats, ki, mi, guess_cw, use_ransac=not trusted, rounds=2, rotation_prior=rotation_prior,
                             weigh_points=with_saved)
            if sol is not None and (best is None or int(sol[1].sum()) > int(best[1].sum())):
                best = (sol[0], sol[1], ki, mi)
            if best is not None and self._confident(int(best[1].sum()), best[2].size):
                break
        return best, attempt
