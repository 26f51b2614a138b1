"""What a tracker is to the tracker process: `Tracker` (the protocol both backends implement), the
per-frame `TrackResult` and its `TrackingState`.

The native `RgbdSlam` (tracker/slam.py) and `OrbSlam3Odometry` (tracker.orbslam3) both satisfy
`Tracker`; tracker.node works against the protocol only.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from octolog.kit.geometry import RgbdFrame


class TrackingState(enum.StrEnum):
    """A frame's tracking state. The values are the strings logged and the names of the
    `TrackingStatus` message's constants (INIT=0, OK=1, LOST=2, SKIPPED=3, INERTIAL=4), which are the wire codes."""

    INIT = "INIT"  # the first keyframe was made from this frame (the world origin)
    OK = "OK"  # pose estimated against the map
    LOST = "LOST"  # no reliable pose: the motion model's prediction is reported
    SKIPPED = "SKIPPED"  # tracker.node only: a live tracker took a newer frame, this one was not tracked
    INERTIAL = "INERTIAL"  # vision could not place the frame: the pose is the IMU's, propagated from the last one


class KeypointState(enum.IntEnum):
    """What became of a keypoint of the last frame (`Tracker.keypoints`), for the viewer's colours."""

    UNMATCHED = 0
    OUTLIER = 1  # matched to a map point, rejected by the pose
    TRACKED = 2  # an inlier of the pose
    NEW = 3  # created a new map point (keyframes only)


@dataclass(frozen=True)
class TrackResult:
    """The tracker's answer for one frame."""

    seq: int
    stamp_ns: int
    world_from_camera: np.ndarray  # (4, 4) float64; world = first keyframe's camera frame
    state: TrackingState
    is_keyframe: bool
    keyframe_id: int  # -1 unless is_keyframe
    n_matches: int
    n_inliers: int
    # keyframes the back end moved (loop closure), id -> corrected world_from_camera; empty if none
    corrected: dict[int, np.ndarray] = field(default_factory=dict)
    # (new keyframe id, old keyframe id) of a loop closed at this frame
    loop: tuple[int, int] | None = None
    relocalised: bool = False
    # root mean square reprojection error of the inlier matches, in pixels of each keypoint's
    # pyramid level (a fit quality with no ground truth: ~1 for a model that explains the image)
    residual: float = float("nan")
    # a keyframe inserted without the back end's pending result (live, the back end busy; see
    # RgbdSlam.defer_backend): the result is applied at a later keyframe
    backend_deferred: bool = False
    # how far the back end's correction, applied at this keyframe, moved the frame's pose (m): the
    # map was corrected under it, so its step from the previous pose is that much more than motion
    map_moved_m: float = 0.0
    # the depth camera's bias correction this frame's readings took (1/m: 1/z <- 1/z - offset), the
    # one its keyframe and `corrected` carry to the mapper (tracker.depth)
    depth_inverse_offset: float = 0.0
    # in a saved map not found yet (tracker/slam.py: SavedMapSearch): this frame made a keyframe of a map not yet
    # placed, keep the frame (`hold`); keyframes placed at this frame, id -> (the frame seq they were
    # made from, world_from_camera): send them now, from the frames kept
    hold: bool = False
    placed: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)


@runtime_checkable
class Tracker(Protocol):
    """An RGB-D tracker: `track` once per frame in time order, `finish` once at the end of the stream."""

    @property
    def n_keyframes(self) -> int: ...

    def prepare(self, frame: RgbdFrame) -> object:
        """The work on `frame` that needs nothing but its pixels (feature extraction), safe to run on
        one other thread ahead of `track`; None when there is none. Results do not depend on it. Opaque
        to the caller: only this tracker's `track` reads it."""
        ...

    def track(self, frame: RgbdFrame, prepared: object = None) -> TrackResult:
        """Estimate world_from_camera of `frame` (with what `prepare(frame)` returned, if called);
        raises TrackingError for a frame that contradicts its camera, never for bad image content."""
        ...

    def finish(self) -> dict[int, np.ndarray]:
        """End of stream: let any back end finish; returns the keyframes it moved (id -> pose)."""
        ...

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Current world_from_camera of every keyframe published so far."""
        ...

    def trajectory(self) -> tuple[list[int], list[np.ndarray]]:
        """Stamps and final world_from_camera of the frames the trajectory file lists."""
        ...

    def keypoints(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Raw pixels of the last frame's keypoints and their `KeypointState`s; None if not exposed."""
        ...

    def local_map(self) -> np.ndarray | None:
        """World positions of the map points the last frame was matched against; None if not exposed."""
        ...
