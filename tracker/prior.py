"""Tracking in a map an earlier session saved (tracker/mapfile.py): `--map`, and `tracker.mode`.

`adopt_map` takes the saved keyframes, points and loops before the first frame; the place index is
made again from the keyframes' descriptors. Until the camera is found in the map, every frame is
tried by place recognition alone (`relocalisation_guess`, then the pose against the map, on the
evidence a relocalisation needs: `tracking.relocalise_min_inliers`) and reported LOST, while a
map of its own (a second `RgbdSlam`, `_sandbox`) tracks it in its own world; the keyframes it makes
are held back (`TrackResult.hold`: the node keeps their frames). Found, at frame f, the held map is
placed in the saved one by the two poses of frame f (world_from_own = saved pose @ own pose^-1):
its keyframes, numbered after the saved ones, and its points join the map, the frames it tracked
join the trajectory, and the held keyframes go out at their placed poses (`TrackResult.placed`);
tracking goes on in the saved map's world and, in `map` mode, extends it. Not found within
`map_find_frames` frames, the tracker gives the saved map up: the held map becomes the map (its
keyframes go out numbered from 0, in its own world: `prior_dropped`). In `localize` mode no
keyframe is made and nothing of the map changes: nothing is held, and the camera is looked for
until the stream ends.

A mixin of `RgbdSlam` (tracker.odometry), which owns the map and the motion state.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

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
    prior_dropped = False  # not found within map_find_frames: tracking went on in a map of its own
    prior_placed = 0  # keyframes of the map of its own placed in the saved one when found
    _sandbox: Any = None  # the map of its own while the camera is not found (an RgbdSlam)
    _held: dict[int, int] = {}  # its keyframes: id -> frame seq

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
        self._held = {}

    def save_map(self, path: Path) -> None:
        """Write the map as it stands (after `finish`: the final bundle adjustment) to `path`."""
        if self._intrinsics is None:
            raise TrackingError("no map to save: no frame was tracked")
        save_map(path, intrinsics=self._intrinsics, keyframes=self._keyframes, points=self._map,
                 loop_edges=self._loop_edges, depth_offset=self.depth_offset)

    def _find_in_prior(self, frame: RgbdFrame, feats: FrameFeatures, extracted: Any) -> TrackResult:
        """A frame while the camera is not yet found in the saved map (see the module)."""
        assert self._undistort is not None
        if self.prior_misses == 0 and self._sandbox is None and not self.params.localize:
            # made at the first frame, once the stream's camera has set the parameters
            self._sandbox = type(self)(self.params, vocabulary=self._bow.vocabulary if self._bow else None)
            self._sandbox.depth_offset, self._sandbox.depth_model = self.depth_offset, self.depth_model
        own = self._sandbox.track(frame, (frame, extracted)) if self._sandbox is not None else None
        if own is not None and own.is_keyframe:
            self._held[own.keyframe_id] = frame.seq
        hold = own is not None and own.is_keyframe
        tracked = None
        guess = relocalisation_guess(feats, self._keyframes, self._bow, self.params, self._undistort.K)
        if guess is not None:
            try:
                tracked = self._track_against_map(feats, guess, frame.stamp_ns)
            except (cv2.error, np.linalg.LinAlgError):
                tracked = None
        if tracked is None or tracked.n_inliers < self.params.tracking.relocalise_min_inliers:
            self.prior_misses += 1
            if self.prior_misses >= self.params.map_find_frames and not self.params.localize:
                return self._give_up(frame, own)  # localizing keeps looking: it makes no map of its own
            return TrackResult(frame.seq, frame.stamp_ns, np.eye(4), TrackingState.LOST, False, -1, 0, 0, hold=hold)
        pose = invert(tracked.camera_from_world)
        placed: dict[int, tuple[int, np.ndarray]] = {}
        if own is not None and own.state != TrackingState.LOST:
            placed = self._place_own(pose, own.world_from_camera)
        self._sandbox = None
        if self._frames and self._frames[-1][0] == frame.stamp_ns:  # the map of its own had this frame too
            self._frames.pop()
        ref = self._keyframes[-1]
        self._frames.append((frame.stamp_ns, ref.id, invert(ref.world_from_camera) @ pose))
        self._remember(frame.stamp_ns, pose, continuous=False)
        self.prior_found_at = frame.seq
        return TrackResult(frame.seq, frame.stamp_ns, pose.copy(), TrackingState.OK, False, -1, tracked.n_matches,
                           tracked.n_inliers, relocalised=True, residual=tracked.residual,
                           depth_inverse_offset=self.depth_offset, hold=hold, placed=placed)

    def _place_own(self, pose: np.ndarray, own_pose: np.ndarray) -> dict[int, tuple[int, np.ndarray]]:
        """The map of its own into the saved one, by the frame's pose in each (world_from_own = pose @
        own_pose^-1): keyframes numbered after the saved ones, points after theirs, poses and points
        moved; its tracked frames join the trajectory. Returns the placed keyframes: id -> (frame seq,
        world_from_camera)."""
        own = self._sandbox
        _, _, own_pose = own._sync_backend(own_pose)  # its last back-end result in; the frame moves with it
        W = pose @ invert(own_pose)
        k0, p0, n = len(self._keyframes), self._map.size, own._map.size
        mp = self._map
        mp._grow(p0 + n)
        for name in ("xyz", "desc", "weight", "n_obs", "n_visible", "n_found", "bad", "ref_kf"):
            getattr(mp, name)[p0:p0 + n] = getattr(own._map, name)[:n]
        mp.xyz[p0:p0 + n] = own._map.xyz[:n] @ W[:3, :3].T + W[:3, 3]
        mp.ref_kf[p0:p0 + n] += k0
        mp.size = p0 + n
        placed = {}
        for kf in own._keyframes:
            kf.id += k0
            kf.world_from_camera = W @ kf.world_from_camera
            kf.point_ids, kf.obs_pid = kf.point_ids + p0, kf.obs_pid + p0
            kf.covis = [c + k0 for c in kf.covis]
            self._keyframes.append(kf)
            if self._bow is not None:
                self._bow.add(kf.id, kf.feats.desc)
            placed[kf.id] = (self._held[kf.id - k0], kf.world_from_camera.copy())
        self._kf_pos = np.array([kf.world_from_camera[:3, 3] for kf in self._keyframes]).reshape(-1, 3)
        self._kf_axis = np.array([kf.world_from_camera[:3, 2] for kf in self._keyframes]).reshape(-1, 3)
        self._loop_edges += [(a + k0, b + k0, T) for a, b, T in own._loop_edges]
        self._frames += [(stamp, k + k0, T) for stamp, k, T in own._frames]  # relative: W leaves them
        self.prior_placed = len(placed)
        return placed

    def _give_up(self, frame: RgbdFrame, own: TrackResult | None) -> TrackResult:
        """Not found in time: the map of its own becomes the map (the saved one is left as it was, it
        is not this session's world); its held keyframes go out, numbered from 0."""
        self.prior_dropped = True
        sandbox, self._sandbox = self._sandbox, None
        if own is None:  # no map of its own to go on in: one from the next frame
            self._map, self._keyframes, self._loop_edges, self._frames = MapPoints(), [], [], []
            self._kf_pos, self._kf_axis = np.zeros((0, 3)), np.zeros((0, 3))
            self._bow = BowIndex(self._bow.vocabulary) if self._bow is not None else None
            return TrackResult(frame.seq, frame.stamp_ns, np.eye(4), TrackingState.LOST, False, -1, 0, 0)
        for name in _MAP_STATE:
            setattr(self, name, getattr(sandbox, name))
        placed = {kf.id: (self._held[kf.id], kf.world_from_camera.copy()) for kf in self._keyframes}
        return replace(own, hold=own.is_keyframe, placed=placed, is_keyframe=False, keyframe_id=-1)


# what a map of its own brings when it becomes the tracker's map (RgbdSlam's map and motion state)
_MAP_STATE = ("_map", "_keyframes", "_kf_pos", "_kf_axis", "_bow", "_loop_edges", "_last_loop_kf", "_loop_candidate",
              "_frames", "_pending", "_last_pose", "_last_stamp", "_last_ok", "_last_inlier_ids", "_velocity",
              "_last_local", "_last_pts", "_last_kp_state", "depth_offset", "depth_corrections", "loops")
