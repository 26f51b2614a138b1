"""The SLAM core's map as tracking sees it: the keyframes and their points, the place index over
the keyframes, which of them are local to a pose, whether a tracked frame adds a keyframe, and its
insertion (depth fused into matched points, new points for the rest, the covisible keyframes).

`LocalMap` owns that state. The back end (tracker/backend.py) works on snapshots of it and its
results come back through `LocalMap.points` and `LocalMap.keyframes` (tracker/backend_handoff.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from octolog.kit.geometry import Intrinsics, invert
from octolog.tracker.config import OdometryParams
from octolog.tracker.features import FrameFeatures
from octolog.tracker.keyframe_map import METRES_PER_RADIAN, Keyframe, MapPoints, depth_weight, keyframe_wanted
from octolog.tracker.places import BowIndex
from octolog.tracker.vocab import Vocabulary

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


class LocalMap:
    """Keyframes, map points and the place index of one SLAM map."""

    def __init__(self, params: OdometryParams, vocabulary: Vocabulary | None = None) -> None:
        self.params = params
        self.points = MapPoints()
        self.keyframes: list[Keyframe] = []
        self.index = BowIndex(vocabulary) if vocabulary is not None else None  # None: every keyframe is a candidate
        self._kf_pos = np.zeros((0, 3))  # each keyframe's position and viewing axis, for `local_keyframes`
        self._kf_axis = np.zeros((0, 3))
        # A saved map's keyframes and points (`adopt`): the first this many. They are the world a
        # later session lives in: the back end never moves them, and in `localize` mode nothing
        # changes them (the keyframes made then are temporary: tracking's, not the map's).
        self.frozen_keyframes = 0
        self.frozen_points = 0

    def __len__(self) -> int:
        return len(self.keyframes)

    @property
    def kf_pos(self) -> np.ndarray:
        return self._kf_pos

    @property
    def kf_axis(self) -> np.ndarray:
        return self._kf_axis

    # -- queries ---------------------------------------------------------------------------------

    def local_keyframes(self, world_from_camera: np.ndarray, count: int) -> np.ndarray:
        """Sorted indices of the `count` keyframes nearest to a pose, always with the newest."""
        n_kf = len(self.keyframes)
        axis = world_from_camera[:3, 2]
        dist = np.linalg.norm(self._kf_pos - world_from_camera[:3, 3], axis=1)
        angle = np.arccos(np.clip(self._kf_axis @ axis, -1.0, 1.0))
        score = dist + METRES_PER_RADIAN * angle
        score[max(0, n_kf - self.params.local_map.n_recent_keyframes) :] = -1.0
        return np.sort(np.lexsort((np.arange(n_kf), score))[:count])

    def local_points(self, world_from_camera: np.ndarray) -> np.ndarray:
        """Sorted ids of good map points seen by the keyframes nearest to a pose plus the newest."""
        kfs = self.local_keyframes(world_from_camera, self.params.local_map.n_keyframes)
        ids = np.unique(np.concatenate([self.keyframes[i].point_ids for i in kfs]))
        return ids[~self.points.bad[ids]]

    def saved_points_in_view(self, world_from_camera: np.ndarray, intr: Intrinsics) -> np.ndarray:
        """Sorted ids of the saved map's good points (`frozen_points`) seen by those of its keyframes
        that made the most points in view from a pose. By view, not by distance: a later session
        walking the other way stands where the saved keyframes looked elsewhere."""
        n = self.frozen_points
        ids = np.flatnonzero(~self.points.bad[:n])
        _, inside = self.project(ids, invert(world_from_camera), intr)
        votes = np.bincount(self.points.ref_kf[ids[inside]], minlength=self.frozen_keyframes)
        kfs = np.lexsort((np.arange(votes.size), -votes))[: self.params.local_map.n_keyframes]
        kfs = kfs[votes[kfs] > 0]
        if not kfs.size:
            return np.zeros(0, np.int64)
        pids = np.unique(np.concatenate([self.keyframes[i].point_ids for i in kfs]))
        pids = pids[pids < n]
        return pids[~self.points.bad[pids]]

    def project(self, ids: np.ndarray, camera_from_world: np.ndarray, intr: Intrinsics
                ) -> tuple[np.ndarray, np.ndarray]:
        """Projected pixels of map points and the mask of those in front of and inside the image."""
        p = self.points.xyz[ids] @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        z = p[:, 2]
        front = z > self.params.depth.min_m * 0.5
        zs = np.where(front, z, 1.0)
        uv = np.empty((ids.size, 2))
        uv[:, 0] = intr.fx * p[:, 0] / zs + intr.cx
        uv[:, 1] = intr.fy * p[:, 1] / zs + intr.cy
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
        return uv, inside

    # -- growth ----------------------------------------------------------------------------------

    def need_keyframe(self, pose: np.ndarray, tracked: TrackedFrame) -> bool:
        """Whether this frame adds to the map. Measured against the reference keyframe, the local
        keyframe that holds most of the frame's inliers (ORB-SLAM's), not the newest: a camera back
        in a place the map already covers adds nothing, so a session that keeps revisiting a room
        keeps a map (and a back end) the size of the room, not of the session."""
        local = self.local_keyframes(pose, self.params.local_map.n_keyframes)
        shared_by = [int(np.isin(tracked.map_idx, self.keyframes[i].point_ids, assume_unique=True).sum())
                     for i in local]
        best = int(np.argmax(shared_by))  # ties: the oldest
        return keyframe_wanted(self.keyframes[int(local[best])], shared_by[best], pose, tracked.feats.z,
                               tracked.kp_idx, self.params.keyframes, max_new_point_m=self.params.depth.max_new_point_m)

    def insert(self, seq: int, pose: np.ndarray, feats: FrameFeatures, tracked: TrackedFrame,
               gyro: tuple[int, np.ndarray, float] | None = None) -> tuple[int, np.ndarray]:
        """Add a keyframe: fuse depth into its matched points, create points for the rest. Returns
        its id and the keypoints that made new points."""
        mp, local = self.points, self.params.local_map
        R, t = pose[:3, :3], pose[:3, 3]
        z = feats.z
        kp_m, ids_m = tracked.kp_idx, tracked.map_idx
        # tracker.mode = "localize": the saved map's points stay as they were
        keep = self.frozen_points if self.params.localize else 0
        mine = ids_m >= keep
        with_d = (z[kp_m] > 0.0) & mine
        if local.fuse_depth and np.any(with_d):
            k = kp_m[with_d]
            mp.fuse(ids_m[with_d], feats.xyz[k] @ R.T + t, depth_weight(z[k]))
        # The newest appearance matches the next frames best.
        mp.desc[ids_m[mine]] = feats.desc[kp_m[mine]]
        mp.n_obs[ids_m[mine]] += 1

        kf_id = len(self.keyframes)
        fresh = np.ones(len(feats), dtype=bool)
        fresh[kp_m] = False
        fresh &= (z > 0.0) & (z <= self.params.depth.max_new_point_m)
        k = np.flatnonzero(fresh)
        new_ids = mp.add(feats.xyz[k] @ R.T + t, feats.desc[k], depth_weight(z[k]), kf_id)

        mp.cull(local.cull_min_visible, local.cull_min_found_ratio, keep=keep)

        point_ids = np.unique(np.concatenate([ids_m, new_ids]))
        shared = np.bincount(mp.ref_kf[ids_m], minlength=kf_id) if ids_m.size else np.zeros(kf_id, np.int64)
        covis = [int(j) for j in np.lexsort((np.arange(shared.size), -shared))[:COVIS_NEIGHBOURS]
                 if shared[j] >= COVIS_MIN_SHARED_POINTS]
        if self.index is not None:
            self.index.add(kf_id, feats.desc)
        self.keyframes.append(Keyframe(kf_id, seq, pose.copy(), point_ids, feats,
                                       np.concatenate([kp_m, k]), np.concatenate([ids_m, new_ids]), sorted(covis),
                                       gyro=gyro))
        self._kf_pos = np.vstack([self._kf_pos, t[None, :]])
        self._kf_axis = np.vstack([self._kf_axis, R[:, 2][None, :]])
        return kf_id, k

    # -- whole-map changes -----------------------------------------------------------------------

    def adopt(self, points: MapPoints, keyframes: list[Keyframe]) -> None:
        """A saved map's points and keyframes as this map (before any frame); the index made anew."""
        self.points, self.keyframes = points, keyframes
        self.frozen_keyframes, self.frozen_points = len(keyframes), points.size
        self.reindex_poses()
        if self.index is not None:
            for kf in keyframes:
                self.index.add(kf.id, kf.feats.desc)

    def reindex_poses(self) -> None:
        """Every keyframe's position and axis read again from its pose."""
        self._kf_pos = np.array([kf.world_from_camera[:3, 3] for kf in self.keyframes]).reshape(-1, 3)
        self._kf_axis = np.array([kf.world_from_camera[:3, 2] for kf in self.keyframes]).reshape(-1, 3)

    def scale_positions(self, s: float) -> None:
        """The keyframe positions scaled by `s` (their poses are scaled by the caller)."""
        self._kf_pos *= s

    def place(self, other: LocalMap, world_from_other: np.ndarray) -> tuple[int, int]:
        """Another map's keyframes and points into this one, moved by `world_from_other`: keyframes
        numbered after this map's, points after its points. Returns (first keyframe id, first point id)."""
        W = world_from_other
        k0, p0, n = len(self.keyframes), self.points.size, other.points.size
        mp = self.points
        mp._grow(p0 + n)
        for name in ("xyz", "desc", "weight", "n_obs", "n_visible", "n_found", "bad", "ref_kf"):
            getattr(mp, name)[p0:p0 + n] = getattr(other.points, name)[:n]
        mp.xyz[p0:p0 + n] = other.points.xyz[:n] @ W[:3, :3].T + W[:3, 3]
        mp.ref_kf[p0:p0 + n] += k0
        mp.size = p0 + n
        for kf in other.keyframes:
            kf.id += k0
            kf.world_from_camera = W @ kf.world_from_camera
            kf.point_ids, kf.obs_pid = kf.point_ids + p0, kf.obs_pid + p0
            kf.covis = [c + k0 for c in kf.covis]
            self.keyframes.append(kf)
            if self.index is not None:
                self.index.add(kf.id, kf.feats.desc)
        self.reindex_poses()
        return k0, p0

    def clear(self) -> None:
        """No keyframes, no points (the index kept empty over the same vocabulary)."""
        self.points, self.keyframes = MapPoints(), []
        self.frozen_keyframes = self.frozen_points = 0
        self._kf_pos, self._kf_axis = np.zeros((0, 3)), np.zeros((0, 3))
        self.index = BowIndex(self.index.vocabulary) if self.index is not None else None

    def take(self, other: LocalMap) -> None:
        """Another map's whole state as this one's (a map of its own becomes the map)."""
        self.points, self.keyframes, self.index = other.points, other.keyframes, other.index
        self.frozen_keyframes, self.frozen_points = other.frozen_keyframes, other.frozen_points
        self._kf_pos, self._kf_axis = other._kf_pos, other._kf_axis
