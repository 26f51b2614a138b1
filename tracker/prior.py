"""Tracking in a map an earlier session saved (tracker/mapfile.py): `--map`, and `tracker.mode`.

`adopt_map` takes the saved keyframes, points and loops before the first frame; the place index is
made again from the keyframes' descriptors. Until the camera is found in the map, every frame is
placed by place recognition alone (`relocalisation_guess`, then the pose against the map, on the
evidence a relocalisation needs: `tracking.relocalise_min_inliers`): found, tracking goes on in the
saved map's world and, in `map` mode, extends it; not found within `map_find_frames` frames, the
tracker says so and starts a map of its own (a separate map, in its own world: `prior_dropped`).
In `localize` mode no keyframe is made and nothing of the map changes.

A mixin of `RgbdSlam` (tracker.odometry), which owns the map and the motion state.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from octolog.kit.errors import TrackingError
from octolog.kit.geometry import RgbdFrame, invert
from octolog.tracker.features import FrameFeatures, Undistorter
from octolog.tracker.interface import TrackingState, TrackResult
from octolog.tracker.keyframe_map import MapPoints
from octolog.tracker.mapfile import SavedMap, save_map
from octolog.tracker.places import BowIndex, relocalisation_guess


class PriorMap:
    """A saved map for `RgbdSlam`: adopt it, find the camera in it."""

    prior_keyframes = 0  # keyframes the saved map brought
    prior_found_at = -1  # the frame seq the camera was first found at in it (-1: not yet, or no map)
    prior_misses = 0  # frames not found in it before that
    prior_dropped = False  # not found within map_find_frames: tracking started a map of its own

    def adopt_map(self, saved: SavedMap) -> None:
        """Track in `saved` from the first frame on (before any frame)."""
        if self._keyframes:
            raise TrackingError("a saved map is taken before the first frame only")
        self._intrinsics, self._undistort = saved.intrinsics, Undistorter(saved.intrinsics)
        self._map, self._keyframes, self._loop_edges = saved.points, saved.keyframes, saved.loop_edges
        self._kf_pos = np.array([kf.world_from_camera[:3, 3] for kf in saved.keyframes]).reshape(-1, 3)
        self._kf_axis = np.array([kf.world_from_camera[:3, 2] for kf in saved.keyframes]).reshape(-1, 3)
        if self._bow is not None:
            for kf in saved.keyframes:
                self._bow.add(kf.id, kf.feats.desc)
        self.depth_offset = saved.depth_offset  # the same camera: its readings take the same correction
        self.prior_keyframes = len(saved.keyframes)
        self._last_pose = None

    def save_map(self, path: Path) -> None:
        """Write the map as it stands (after `finish`: the final bundle adjustment) to `path`."""
        if self._intrinsics is None:
            raise TrackingError("no map to save: no frame was tracked")
        save_map(path, intrinsics=self._intrinsics, keyframes=self._keyframes, points=self._map,
                 loop_edges=self._loop_edges, depth_offset=self.depth_offset)

    def _find_in_prior(self, frame: RgbdFrame, feats: FrameFeatures) -> TrackResult:
        """A frame while the camera is not yet found in the saved map: placed by place recognition,
        else LOST; after `map_find_frames` such frames, the map is dropped for one of its own."""
        assert self._undistort is not None
        tracked = None
        guess = relocalisation_guess(feats, self._keyframes, self._bow, self.params, self._undistort.K)
        if guess is not None:
            try:
                tracked = self._track_against_map(feats, guess, frame.stamp_ns)
            except (cv2.error, np.linalg.LinAlgError):
                tracked = None
        if tracked is None or tracked.n_inliers < self.params.tracking.relocalise_min_inliers:
            self.prior_misses += 1
            if self.prior_misses >= self.params.map_find_frames:
                self._drop_prior()
            return TrackResult(frame.seq, frame.stamp_ns, np.eye(4), TrackingState.LOST, False, -1, 0, 0)
        pose = invert(tracked.camera_from_world)
        ref = self._keyframes[-1]
        self._frames.append((frame.stamp_ns, ref.id, invert(ref.world_from_camera) @ pose))
        self._remember(frame.stamp_ns, pose, continuous=False)
        self.prior_found_at = frame.seq
        return TrackResult(frame.seq, frame.stamp_ns, pose.copy(), TrackingState.OK, False, -1, tracked.n_matches,
                           tracked.n_inliers, relocalised=True, residual=tracked.residual,
                           depth_inverse_offset=self.depth_offset)

    def _drop_prior(self) -> None:
        """Start a map of its own: the saved one is left as it was (it is not this session's world)."""
        self._map, self._keyframes, self._loop_edges = MapPoints(), [], []
        self._kf_pos, self._kf_axis = np.zeros((0, 3)), np.zeros((0, 3))
        if self._bow is not None:
            self._bow = BowIndex(self._bow.vocabulary)
        self.prior_dropped = True
