"""Placing robots in the common world without start poses: the first robot's world is the map's;
every other robot is placed when one of its keyframes verifiably sees a place already in the map
(mapper/align.py), and until then its keyframes wait in its own frame.

Everything happens at defined points of the fleet merge's order (mapper/fleet.py): a keyframe of an
unplaced robot is tried against the placed keyframes when the merge pops it; a placed keyframe,
once integrated, is tried against the waiting keyframes of the unplaced robots (in robot order,
then in their order). So the same streams place the same robots at the same keyframes, and the
map's bytes do not depend on arrival timing. A robot never placed stays out of the map and is
reported unmerged. Features are kept only while some robot is unplaced.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from octolog.kit.geometry import RgbdFrame, invert
from octolog.mapper.align import Alignment, Features, align, features


@dataclass
class Waiting:
    """An unplaced robot's keyframe, in its own world."""

    kf_id: int
    stamp_ns: int
    robot_from_camera: np.ndarray
    frame: RgbdFrame
    features: Features


@dataclass(frozen=True)
class Merge:
    """A robot placed: where, and on what evidence."""

    robot: int
    robot_kf: int  # its keyframe that matched
    map_gid: int  # the map keyframe it matched
    world_from_robot: np.ndarray
    alignment: Alignment


@dataclass
class Placement:
    n_robots: int
    world_from_robot: list[np.ndarray | None] = field(default_factory=list)
    waiting: list[list[Waiting]] = field(default_factory=list)
    merges: list[Merge] = field(default_factory=list)
    _library: list[tuple[int, np.ndarray, Features]] = field(default_factory=list)  # (gid, world_from_camera, f)

    @classmethod
    def known(cls, poses: list[np.ndarray]) -> Placement:
        """Every robot placed by its start pose (mapper.start_poses)."""
        return cls(len(poses), list(poses), [[] for _ in poses])

    @classmethod
    def by_place(cls, n: int) -> Placement:
        """Robot 0's world is the map's; the others wait to be placed."""
        return cls(n, [np.eye(4)] + [None] * (n - 1), [[] for _ in range(n)])

    def placed(self, robot: int) -> bool:
        return self.world_from_robot[robot] is not None

    def _searching(self) -> bool:
        return any(w is None for w in self.world_from_robot)

    def offer(self, robot: int, kf_id: int, stamp_ns: int, robot_from_camera: np.ndarray,
              frame: RgbdFrame) -> Merge | None:
        """An unplaced robot's keyframe: placed against the map's keyframes (the best verified
        match), or kept waiting. The merge, if any; the caller then integrates `take(robot)`."""
        w = Waiting(kf_id, stamp_ns, robot_from_camera, frame, features(frame))
        self.waiting[robot].append(w)
        best = None
        for gid, world_from_cam, f in self._library:
            a = align(f, w.features)
            if a is not None and (best is None or a.inliers > best[2].inliers):
                best = (gid, world_from_cam, a)
        if best is None:
            return None
        return self._place(robot, w, *best)

    def remember(self, gid: int, world_from_camera: np.ndarray, frame: RgbdFrame) -> list[Merge]:
        """A keyframe now in the map: kept for matching while robots are unplaced, and tried against
        their waiting keyframes. The merges it made (robots to `take`)."""
        if not self._searching():
            self._library.clear()
            return []
        f = features(frame)
        self._library.append((gid, world_from_camera, f))
        out = []
        for robot in range(self.n_robots):
            if self.placed(robot):
                continue
            for w in self.waiting[robot]:
                a = align(f, w.features)
                if a is not None:
                    out.append(self._place(robot, w, gid, world_from_camera, a))
                    break
        return out

    def correct(self, robot: int, poses: dict[int, np.ndarray]) -> None:
        """A correction from an unplaced robot's tracker: its waiting keyframes move with it."""
        for w in self.waiting[robot]:
            if w.kf_id in poses:
                w.robot_from_camera = poses[w.kf_id]

    def take(self, robot: int) -> list[Waiting]:
        """A placed robot's waiting keyframes, in their order, to integrate now."""
        out, self.waiting[robot] = self.waiting[robot], []
        return out

    def unplaced(self) -> list[int]:
        return [i for i, w in enumerate(self.world_from_robot) if w is None]

    def _place(self, robot: int, w: Waiting, gid: int, world_from_cam: np.ndarray, a: Alignment) -> Merge:
        world_from_robot = world_from_cam @ a.a_from_b @ invert(w.robot_from_camera)
        self.world_from_robot[robot] = world_from_robot
        m = Merge(robot, w.kf_id, gid, world_from_robot, a)
        self.merges.append(m)
        return m
