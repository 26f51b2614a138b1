"""Every tracked frame's pose, kept relative to the keyframe it was tracked against, so corrections
of the keyframes (bundle adjustment, loop closing, a depth-scale correction) reach every frame."""

from __future__ import annotations

import numpy as np

from octolog.kit.geometry import invert
from octolog.tracker.keyframe_map import Keyframe
from octolog.tracker.motion import scaled


class Trajectory:
    """Per tracked frame: (stamp, reference keyframe id, reference_from_camera)."""

    def __init__(self) -> None:
        self.frames: list[tuple[int, int, np.ndarray]] = []

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, stamp_ns: int, ref: Keyframe, world_from_camera: np.ndarray) -> None:
        """A frame placed at `world_from_camera`, kept relative to keyframe `ref`."""
        self.frames.append((stamp_ns, ref.id, invert(ref.world_from_camera) @ world_from_camera))

    def add_keyframe(self, stamp_ns: int, kf_id: int) -> None:
        """A frame that is keyframe `kf_id` itself."""
        self.frames.append((stamp_ns, kf_id, np.eye(4)))

    def drop_last_at(self, stamp_ns: int) -> None:
        """The newest frame, if it is at `stamp_ns`, goes (it is about to be placed again)."""
        if self.frames and self.frames[-1][0] == stamp_ns:
            self.frames.pop()

    def poses(self, keyframes: list[Keyframe]) -> tuple[list[int], list[np.ndarray]]:
        """Stamps and world_from_camera of every frame, through its keyframe's current pose."""
        return [s for s, _, _ in self.frames], [keyframes[k].world_from_camera @ T for _, k, T in self.frames]

    def scale(self, s: float) -> None:
        """Translations scaled by `s` (a depth-scale correction)."""
        self.frames = [(stamp, k, scaled(T, s)) for stamp, k, T in self.frames]

    def place(self, other: Trajectory, k0: int) -> None:
        """Another map's frames, its keyframes numbered from `k0` (relative poses need no move)."""
        self.frames += [(stamp, k + k0, T) for stamp, k, T in other.frames]

    def take(self, other: Trajectory) -> None:
        self.frames = other.frames
