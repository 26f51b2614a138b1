"""Placing robots in the common world without start poses: the first robot's world is the map's;
every other robot is placed when one of its keyframes verifiably sees a place already in the map
(mapper/align.py), and until then its keyframes wait in its own frame.

Everything happens at defined points of the fleet merge's order (mapper/fleet.py): a keyframe of an
unplaced robot is tried against the placed keyframes when the merge pops it; a placed keyframe,
once integrated, is tried against the waiting keyframes of the unplaced robots (in robot order,
then in their order). So the same streams place the same robots at the same keyframes, and the
map's bytes do not depend on arrival timing. A robot never placed stays out of the map and is
reported unmerged.

One match places a robot with that match's error (1-2 cm, about a degree on TUM). So the seam does
not stay at that, the robot's next keyframes are matched too, against map keyframes of the other
robots, up to REFINE_MATCHES verified matches in all; every match is kept as a link between two
keyframes (`links`), and the mapper settles the links and the robots' own trajectories in one pose
graph (mapper/joint.py). Features are kept only while some robot is unplaced or being refined.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from octolog.kit.geometry import RgbdFrame, invert
from octolog.mapper.align import Alignment, Features, align, features

REFINE_MATCHES = 5  # verified matches whose mean places a robot (the first one places it at once)
# Bounds, so that a robot that never meets the others costs the same per keyframe in minute ten as in
# minute one: the newest LIBRARY map keyframes are kept for matching (~0.5 MB of features each), and
# a new map keyframe is tried against the newest TRIES waiting keyframes of each unplaced robot.
LIBRARY = 200
TRIES = 20


@dataclass
class Waiting:
    """An unplaced robot's keyframe, in its own world."""

    kf_id: int
    stamp_ns: int
    robot_from_camera: np.ndarray
    frame: RgbdFrame
    features: Features | None  # dropped once it is too old to be tried (TRIES)


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
    # every verified match between robots: (map keyframe, robot, that robot's keyframe id, the alignment)
    links: list[tuple[int, int, int, Alignment]] = field(default_factory=list)
    _library: list[tuple[int, int, np.ndarray, Features]] = field(default_factory=list)  # (robot, gid, world_from_camera, f)
    _matches: dict[int, int] = field(default_factory=dict)  # robot -> verified matches that placed or refined it

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
        return any(w is None for w in self.world_from_robot) or any(self._refining(r) for r in self._matches)

    def _refining(self, robot: int) -> bool:
        return 0 < self._matches.get(robot, 0) < REFINE_MATCHES

    def offer(self, robot: int, kf_id: int, stamp_ns: int, robot_from_camera: np.ndarray,
              frame: RgbdFrame) -> Merge | None:
        """An unplaced robot's keyframe: placed against the map's keyframes (the best verified
        match), or kept waiting. The merge, if any; the caller then integrates `take(robot)`."""
        w = Waiting(kf_id, stamp_ns, robot_from_camera, frame, features(frame))
        self.waiting[robot].append(w)
        if len(self.waiting[robot]) > TRIES:
            self.waiting[robot][-TRIES - 1].features = None
        best = None
        for _, gid, world_from_cam, f in self._library:
            a = align(f, w.features)
            if a is not None and (best is None or a.inliers > best[2].inliers):
                best = (gid, world_from_cam, a)
        if best is None:
            return None
        return self._place(robot, w, *best)

    def remember(self, robot_of: int, kf_id: int, gid: int, world_from_camera: np.ndarray,
                 frame: RgbdFrame) -> tuple[list[Merge], bool]:
        """A keyframe of robot `robot_of` (its id `kf_id`, the map's `gid`) now in the map: kept for
        matching while robots are unplaced or refined, tried against their waiting keyframes, and, if
        its robot is being refined, against the other robots' map keyframes. The merges it made
        (robots to `take`), and whether it added a link (the joint pose graph has more to settle)."""
        if not self._searching():
            self._library.clear()
            return [], False
        f = features(frame)
        linked = self._refine(robot_of, kf_id, f) if self._refining(robot_of) else False
        self._library.append((robot_of, gid, world_from_camera, f))
        del self._library[:-LIBRARY]
        out = []
        for robot in range(self.n_robots):
            if self.placed(robot):
                continue
            for w in self.waiting[robot][-TRIES:]:
                if w.features is None:
                    continue
                a = align(f, w.features)
                if a is not None:
                    out.append(self._place(robot, w, gid, world_from_camera, a))
                    break
        return out, linked

    def _refine(self, robot: int, kf_id: int, f: Features) -> bool:
        """One more link for `robot` from its keyframe `kf_id`: the best verified match with another
        robot's map keyframe; False without one."""
        best = None
        for other, gid, _, g in self._library:
            if other == robot:
                continue
            a = align(g, f)
            if a is not None and (best is None or a.inliers > best[1].inliers):
                best = (gid, a)
        if best is None:
            return False
        self.links.append((best[0], robot, kf_id, best[1]))
        self._matches[robot] += 1
        return True

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
        self.links.append((gid, robot, w.kf_id, a))
        self._matches[robot] = 1
        m = Merge(robot, w.kf_id, gid, world_from_robot, a)
        self.merges.append(m)
        return m
