"""The tracker's map: map points and the keyframes that observe them.

The SLAM core (tracker/slam.py: its `LocalMap`) grows and edits it; the back end (tracker.backend) reads snapshots
of it and returns corrections that the front end applies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from octolog.kit.geometry import invert
from octolog.tracker.config import KeyframeParams
from octolog.tracker.features import DESCRIPTOR_BYTES, FrameFeatures
from octolog.tracker.pose import rotation_angle

# Initial capacity of the point store (rows); it doubles whenever it fills up.
INITIAL_CAPACITY = 4096
# Points observed by fewer keyframes than this may be retired by `MapPoints.cull`.
CULL_MAX_OBSERVATIONS = 3


def depth_weight(z: np.ndarray) -> np.ndarray:
    """Information of a depth reading: Kinect-type noise grows with the square of the depth."""
    return 1.0 / (z * z) ** 2


class MapPoints:
    """Growable column store of map points (world position, descriptor, bookkeeping)."""

    def __init__(self) -> None:
        self.size = 0
        cap = INITIAL_CAPACITY
        self.xyz = np.zeros((cap, 3))
        self.desc = np.zeros((cap, DESCRIPTOR_BYTES), np.uint8)
        self.weight = np.zeros(cap)
        self.n_obs = np.zeros(cap, np.int32)
        self.n_visible = np.zeros(cap, np.int32)
        self.n_found = np.zeros(cap, np.int32)
        self.bad = np.zeros(cap, bool)
        self.ref_kf = np.zeros(cap, np.int64)  # keyframe that created the point

    def _grow(self, need: int) -> None:
        cap = self.xyz.shape[0]
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        for name in ("xyz", "desc", "weight", "n_obs", "n_visible", "n_found", "bad", "ref_kf"):
            old = getattr(self, name)
            arr = np.zeros((new_cap,) + old.shape[1:], old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def add(self, xyz: np.ndarray, desc: np.ndarray, weight: np.ndarray, ref_kf: int) -> np.ndarray:
        n = xyz.shape[0]
        self._grow(self.size + n)
        ids = np.arange(self.size, self.size + n)
        self.xyz[ids] = xyz
        self.desc[ids] = desc
        self.weight[ids] = weight
        self.n_obs[ids] = 1
        self.ref_kf[ids] = ref_kf
        self.size += n
        return ids

    def fuse(self, ids: np.ndarray, xyz: np.ndarray, weight: np.ndarray) -> None:
        """Average new world positions of points `ids` into them, weighted by information."""
        w_new = weight
        w_old = self.weight[ids]
        self.xyz[ids] = (self.xyz[ids] * w_old[:, None] + xyz * w_new[:, None]) / (w_old + w_new)[:, None]
        self.weight[ids] = w_old + w_new

    def cull(self, min_visible: int, min_found_ratio: float, keep: int = 0) -> None:
        """Retire points that are seen in view but rarely matched: likely bad depth or repeats (the
        first `keep` never: a saved map localized in)."""
        n = self.size
        bad = (self.n_visible[keep:n] >= min_visible) & (self.n_found[keep:n] < min_found_ratio * self.n_visible[keep:n])
        self.bad[keep:n] |= bad & (self.n_obs[keep:n] < CULL_MAX_OBSERVATIONS)

    def first(self, n: int) -> MapPoints:
        """The first `n` points (views of the arrays: a saved map's part of this one, for writing)."""
        head = MapPoints.__new__(MapPoints)
        for name in ("xyz", "desc", "weight", "n_obs", "n_visible", "n_found", "bad", "ref_kf"):
            setattr(head, name, getattr(self, name)[:n])
        head.size = n
        return head


# Keyframes are ranked by distance + this many metres per radian of viewing-direction change (the
# local map; loop candidates without a vocabulary): roughly how far a move changes the view as much
# as a turn does.
METRES_PER_RADIAN = 0.3

@dataclass
class Keyframe:
    """A keyframe: its pose, its keypoints and which map points they observe."""

    id: int
    seq: int
    world_from_camera: np.ndarray
    point_ids: np.ndarray  # sorted unique map point ids this keyframe observes
    feats: FrameFeatures  # all its keypoints (for bundle adjustment, loop detection, relocalisation)
    obs_kp: np.ndarray  # keypoint index of each observation
    obs_pid: np.ndarray  # map point id of each observation
    covis: list[int] = field(default_factory=list)  # earlier keyframes it shares many points with
    # Points of this keyframe matched in the first frame it was the reference keyframe of: the
    # overlap baseline later frames are compared with to decide when the view has changed enough.
    baseline_overlap: int = -1
    # The gyro's rotation from an earlier keyframe: (its id, camera_earlier_from_camera rotation,
    # sigma in rad), a factor of the back end's bundle adjustment (None: no IMU over the interval)
    gyro: tuple[int, np.ndarray, float] | None = None


def keyframe_wanted(ref: Keyframe, shared: int, pose: np.ndarray, z: np.ndarray, tracked_kp: np.ndarray,
                    params: KeyframeParams, *, max_new_point_m: float) -> bool:
    """Whether a tracked frame at `pose` becomes a keyframe, measured against its reference keyframe
    `ref`, with which it shares `shared` inliers; `z` is the depth of each of its keypoints (0: none)
    and `tracked_kp` the keypoints that are inliers. Sets `ref.baseline_overlap` the first time."""
    rel = invert(ref.world_from_camera) @ pose
    if float(np.linalg.norm(rel[:3, 3])) > params.translation_m \
            or rotation_angle(rel[:3, :3]) > math.radians(params.rotation_deg):
        return True
    if params.close_tracked > 0:  # ORB-SLAM's rule for depth cameras: too few near points tracked
        close = (z > 0.0) & (z <= max_new_point_m)
        n_tracked = int(close[tracked_kp].sum())
        if n_tracked < params.close_tracked and int(close.sum()) - n_tracked > params.close_untracked:
            return True
    if ref.baseline_overlap < 0:
        ref.baseline_overlap = shared
    return shared < params.min_overlap * ref.baseline_overlap
