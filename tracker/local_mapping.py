"""The tracker's local mapping: whether a tracked frame becomes a keyframe, and its insertion into the
map (depth fused into matched points, new points for the rest, the covisible keyframes).

A mixin of `RgbdSlam` (tracker.odometry), which owns the map state these methods read and extend.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from octolog.tracker.features import FrameFeatures
from octolog.tracker.interface import KeypointState
from octolog.tracker.keyframe_map import Keyframe, depth_weight, keyframe_wanted

# A keyframe's covisible neighbours (pose-graph edges): at most this many, sharing at least that many points.
COVIS_NEIGHBOURS = 3
COVIS_MIN_SHARED_POINTS = 30


@dataclass
class TrackedFrame:
    """Outcome of matching and pose estimation for one frame."""

    camera_from_world: np.ndarray
    kp_idx: np.ndarray  # keypoint indices of inlier matches
    map_idx: np.ndarray  # map point ids of inlier matches
    n_matches: int
    n_inliers: int
    feats: FrameFeatures  # the keypoints the pose was fitted to (moved to mid-readout: rolling shutter)
    residual: float = float("nan")  # RMS level-scaled reprojection error of the inliers


class LocalMapping:
    """Keyframe decision and insertion for `RgbdSlam`."""

    def _need_keyframe(self, pose: np.ndarray, tracked: TrackedFrame) -> bool:
        """Whether this frame adds to the map. Measured against the reference keyframe, the local
        keyframe that holds most of the frame's inliers (ORB-SLAM's), not the newest: a camera back
        in a place the map already covers adds nothing, so a session that keeps revisiting a room
        keeps a map (and a back end) the size of the room, not of the session."""
        if self.params.localize:  # tracker.mode = "localize": the map stays as it was
            return False
        local = self._local_keyframes(pose, self.params.local_map.n_keyframes)
        shared_by = [int(np.isin(tracked.map_idx, self._keyframes[i].point_ids, assume_unique=True).sum())
                     for i in local]
        best = int(np.argmax(shared_by))  # ties: the oldest
        return keyframe_wanted(self._keyframes[int(local[best])], shared_by[best], pose, tracked.feats.z,
                               tracked.kp_idx, self.params.keyframes, max_new_point_m=self.params.depth.max_new_point_m)

    def _insert_keyframe(self, seq: int, stamp_ns: int, pose: np.ndarray, feats: FrameFeatures,
                         tracked: TrackedFrame) -> int:
        """Add a keyframe: fuse depth into its matched points, create points for the rest."""
        mp, local = self._map, self.params.local_map
        R, t = pose[:3, :3], pose[:3, 3]
        z = feats.z
        kp_m, ids_m = tracked.kp_idx, tracked.map_idx
        with_d = z[kp_m] > 0.0
        if local.fuse_depth and np.any(with_d):
            k = kp_m[with_d]
            mp.fuse(ids_m[with_d], feats.xyz[k] @ R.T + t, depth_weight(z[k]))
        # The newest appearance matches the next frames best.
        mp.desc[ids_m] = feats.desc[kp_m]
        mp.n_obs[ids_m] += 1

        kf_id = len(self._keyframes)
        fresh = np.ones(len(feats), dtype=bool)
        fresh[kp_m] = False
        fresh &= (z > 0.0) & (z <= self.params.depth.max_new_point_m)
        k = np.flatnonzero(fresh)
        new_ids = mp.add(feats.xyz[k] @ R.T + t, feats.desc[k], depth_weight(z[k]), kf_id)
        if self._last_kp_state.size == len(feats):
            self._last_kp_state[k] = KeypointState.NEW

        mp.cull(local.cull_min_visible, local.cull_min_found_ratio)

        point_ids = np.unique(np.concatenate([ids_m, new_ids]))
        shared = np.bincount(mp.ref_kf[ids_m], minlength=kf_id) if ids_m.size else np.zeros(kf_id, np.int64)
        covis = [int(j) for j in np.lexsort((np.arange(shared.size), -shared))[:COVIS_NEIGHBOURS]
                 if shared[j] >= COVIS_MIN_SHARED_POINTS]
        if self._bow is not None:
            self._bow.add(kf_id, feats.desc)
        self._keyframes.append(Keyframe(kf_id, seq, pose.copy(), point_ids, feats,
                                         np.concatenate([kp_m, k]), np.concatenate([ids_m, new_ids]), sorted(covis),
                                         gyro=self._imu_keyframe(kf_id, stamp_ns)))
        self._kf_pos = np.vstack([self._kf_pos, t[None, :]])
        self._kf_axis = np.vstack([self._kf_axis, R[:, 2][None, :]])
        return kf_id
