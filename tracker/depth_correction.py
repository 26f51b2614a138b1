"""The depth camera's bias corrected while tracking (`tracker.depth.correct_bias`).

Every `CHECK_EVERY` keyframes the front end fits the bias to the newest `WINDOW` keyframes'
readings (tracker/depth_bias.py). Once the fit is confident (three standard errors from zero), the
offset it found is added to the correction every later reading takes (1/z <- 1/z - offset), and the
map is made to agree with it at once: every keyframe's readings are re-corrected, the keyframes'
translations scaled by the fit's scale about the world origin (where the first keyframe is), each
map point moved by the scale and by the mean change of its readings, weighted by their information.
The back end's next bundle adjustments start from there. Every keyframe has moved, so all of them
go out as a correction (KeyframePoses, with the new offset: the mapper re-corrects their depth).

A camera with no bias gives fits that are not confident: nothing changes. Off by default: on the
TUM freiburg1 Kinect the fit is confident and wrong (docs/results.md), as a depth error that is not
one disparity offset can be.

`DepthCorrection` owns the correction every reading takes and how often it changed; it moves the map's
keyframes and points itself, and tells the SLAM core the scale by which the other parts' poses move.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.depthmodel import DepthModel
from octolog.tracker.config import OdometryParams
from octolog.tracker.depth_bias import DepthBias, bias_from_map
from octolog.tracker.features import FrameFeatures
from octolog.tracker.keyframe_map import depth_weight
from octolog.tracker.local_map import LocalMap

# the bias is fitted at every this many keyframes, from the newest WINDOW (bounded front-end time:
# about 20 ms for 40 keyframes here), once the map has MIN_KEYFRAMES
CHECK_EVERY = 10
WINDOW = 40
MIN_KEYFRAMES = 20


def recorrected(feats: FrameFeatures, delta: float) -> FrameFeatures:
    """`feats` with every depth reading corrected by `delta` more: 1/z <- 1/z - delta."""
    has = feats.z > 0.0
    factor = np.where(has, 1.0 / np.where(has, 1.0 - delta * feats.z, 1.0), 1.0)
    return FrameFeatures(uv=feats.uv, octave=feats.octave, desc=feats.desc, z=feats.z * factor,
                         xyz=feats.xyz * factor[:, None])


class DepthCorrection:
    """The depth camera's bias: the correction readings take, found and applied online (see the module)."""

    def __init__(self, params: OdometryParams) -> None:
        self.params = params
        # the correction every reading takes now (1/m): the configured one plus what was found
        self.offset = params.depth.inverse_offset
        self.corrections = 0  # how many times the map was corrected
        self.model: DepthModel | None = None  # the camera's depth error model, when the stream says it

    def bias(self, local_map: LocalMap) -> DepthBias | None:
        """The depth camera's systematic error as the map has it (tracker/depth_bias.py), or None:
        what is left in the readings after the correction they took (`corrected`), and the camera's."""
        estimate = bias_from_map(local_map.keyframes, local_map.points.xyz)
        if estimate is None:
            return None
        return estimate.after(self.offset, self.corrections, self.model.fb if self.model is not None else 0.0)

    def found(self, local_map: LocalMap) -> DepthBias | None:
        """A confident bias in the newest keyframes' readings, when a check is due; else None."""
        n = len(local_map.keyframes)
        if not self.params.depth.correct_bias or n < MIN_KEYFRAMES or n % CHECK_EVERY:
            return None
        estimate = bias_from_map(local_map.keyframes[-WINDOW:], local_map.points.xyz)
        if estimate is None or not estimate.confident:
            return None
        # a correction that would take more than half of a reading at the range limit is not a bias
        return estimate if abs(self.offset + estimate.inverse_offset) * self.params.depth.max_m < 0.5 else None

    def correct(self, local_map: LocalMap, found: DepthBias) -> float:
        """Correct the map by a confident bias `found` in it (see the module): every keyframe's
        readings and translation, every point, and the offset later readings take. Returns the
        scale by which every other translation in the map's world must move."""
        delta, s = found.inverse_offset, found.scale
        mp, n = local_map.points, local_map.points.size
        shift = np.zeros((n, 3))
        wsum = np.zeros(n)
        for kf in local_map.keyframes:
            old = kf.feats
            kf.feats = recorrected(old, delta)
            kf.world_from_camera[:3, 3] *= s
            z = old.z[kf.obs_kp]
            d = z > 0.0
            w = depth_weight(z[d])
            moved = (kf.feats.xyz[kf.obs_kp[d]] - old.xyz[kf.obs_kp[d]]) @ kf.world_from_camera[:3, :3].T
            np.add.at(shift, kf.obs_pid[d], moved * w[:, None])
            np.add.at(wsum, kf.obs_pid[d], w)
        mp.xyz[:n] = mp.xyz[:n] * s + shift / np.maximum(wsum, 1e-300)[:, None]
        local_map.scale_positions(s)
        self.offset += delta
        self.corrections += 1
        return s

    def take(self, other: DepthCorrection) -> None:
        """Another map's correction (a map of its own becomes the map)."""
        self.offset, self.corrections = other.offset, other.corrections
