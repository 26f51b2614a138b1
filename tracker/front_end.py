"""The SLAM core's front end on one frame alone: the frame checked against its camera, ORB features
spread over the image, their depth read (and corrected by the depth camera's known bias), their
pixels undistorted and, with a rolling shutter, moved to mid-readout.

`FrontEnd` owns the camera and the extractors, and the last frame's raw keypoints and their
`KeypointState`s (what the viewer shows).
"""

from __future__ import annotations

from functools import partial

import numpy as np

from octolog.kit.errors import TrackingError
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.tracker.config import OdometryParams
from octolog.tracker.features import FrameFeatures, OrbExtractor, Undistorter, backproject, grey_image, lookup_depth
from octolog.tracker.motion import Velocity
from octolog.tracker.pose import unroll_rolling_shutter

Extracted = tuple[np.ndarray, np.ndarray, np.ndarray]  # raw pixels, octaves, descriptors


class FrontEnd:
    """Features of one camera stream's frames; `prepare` may run on one other thread ahead of `features`."""

    def __init__(self, params: OdometryParams) -> None:
        self.params = params
        f = params.features
        make = partial(OrbExtractor, n_features=params.n_features, grid_cols=f.grid_cols, grid_rows=f.grid_rows,
                       fast_threshold=f.fast_threshold, min_fast_threshold=f.min_fast_threshold,
                       n_levels=f.n_levels, scale_factor=f.scale_factor)
        self._extractor, self._extractor_ahead = make(), make()  # the second for `prepare`'s thread
        self.intrinsics: Intrinsics | None = None
        self._undistort: Undistorter | None = None
        self.pts = np.zeros((0, 2))  # the last frame's keypoints, raw pixels
        self.kp_state = np.zeros(0, np.uint8)  # and their KeypointState

    @property
    def K(self) -> np.ndarray:
        """The camera matrix of the undistorted pixels."""
        assert self._undistort is not None
        return self._undistort.K

    def set_camera(self, intr: Intrinsics) -> None:
        self.intrinsics, self._undistort = intr, Undistorter(intr)

    def prepare(self, frame: RgbdFrame) -> tuple[RgbdFrame, Extracted] | None:
        """The frame's ORB features, on the other thread's extractor: pure."""
        try:
            return frame, self._extractor_ahead.extract(grey_image(frame))
        except TrackingError:
            return None  # `track` raises it, in its turn

    def extract(self, frame: RgbdFrame, prepared: tuple[RgbdFrame, Extracted] | None, *, map_made: bool) -> Extracted:
        """The frame's ORB features (those `prepare` made for it, if any), after checking it against
        the camera; TrackingError when it cannot match the camera of a map already made."""
        gray = grey_image(frame)
        intr = frame.intrinsics
        if intr != self.intrinsics:
            if self.intrinsics is not None and map_made:
                raise TrackingError(f"frame {frame.seq}: intrinsics {intr} differ from the map's "
                                    f"{self.intrinsics}: another camera or resolution")
            self.set_camera(intr)
        return prepared[1] if prepared is not None and prepared[0] is frame else self._extractor.extract(gray)

    def features(self, frame: RgbdFrame, extracted: Extracted, depth_offset: float) -> FrameFeatures:
        """Keypoints with depth (each reading corrected by `depth_offset`: 1/z <- 1/z - offset),
        undistorted pixels and camera-frame points; they become the last frame's keypoints."""
        assert self._undistort is not None
        pts, octave, desc = extracted
        d = self.params.depth
        z = lookup_depth(frame.depth, frame.depth_scale_m, pts, min_depth_m=d.min_m, max_depth_m=d.max_m,
                         max_spread=d.edge_spread)
        if depth_offset:
            z = z / (1.0 - depth_offset * z)  # 0 stays 0
        uv = self._undistort(pts)
        self.pts = pts
        self.kp_state = np.zeros(len(pts), np.uint8)
        return FrameFeatures(uv=uv, octave=octave, desc=desc, z=z, xyz=backproject(uv, z, self._undistort.K))

    def unroll(self, feats: FrameFeatures, step: Velocity) -> FrameFeatures:
        """`feats` moved to mid-readout with the camera's motion `step` (tracker/pose.py: unroll_rolling_shutter)."""
        assert self._undistort is not None and self.intrinsics is not None
        return unroll_rolling_shutter(feats, self.pts[:, 1], self.intrinsics.height, self._undistort.K,
                                      self.params.readout_s, step)

    def mark(self, kp_idx: np.ndarray, state: int) -> None:
        """Set the state of some of the last frame's keypoints (when it has them all)."""
        self.kp_state[kp_idx] = state

    def take(self, other: FrontEnd) -> None:
        """Another front end's last keypoints (a map of its own becomes the map)."""
        self.pts, self.kp_state = other.pts, other.kp_state
