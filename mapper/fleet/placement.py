"""Placing robots in the common world without start poses: the first robot's world is the map's;
every other robot is placed when one of its keyframes verifiably sees a place already in the map
(mapper/fleet/align.py), and until then its keyframes wait in its own frame.

Everything happens at defined points of the fleet merge's order (mapper/fleet/order.py): a keyframe of an
unplaced robot is tried against the placed keyframes when the merge pops it; a placed keyframe,
once integrated, is tried against the waiting keyframes of the unplaced robots (in robot order,
then in their order). So the same streams place the same robots at the same keyframes, and the
map's bytes do not depend on arrival timing. A robot never placed stays out of the map and is
reported unmerged.

One match places a robot with that match's error (1-2 cm, about a degree on TUM). So the seam does
not stay at that, the robot's next keyframes are matched too, against map keyframes of the other
robots, up to REFINE_MATCHES verified matches in all; every match is kept as a link between two
keyframes (`links`), and the mapper settles the links and the robots' own trajectories in one pose
graph (mapper/fleet/joint_graph.py).

Robots that meet again later are linked again (`_relink`, the inter-robot loop closure of
multi-session SLAM): map keyframes are kept, one per robot, 0.5 m cell of the world and viewing
direction (the newest; PLACES in all, the oldest dropped first), and a placed robot's keyframe, once
its robot has come `relink_after_m` along its path since its last link, is matched against the
nearest of the other robots' kept keyframes (within RELINK_NEAR_M and RELINK_ANGLE_DEG, in the
common world as it stands). A verified match is one more link, and the joint graph settles again.
With known start poses nothing is matched (as before).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from octolog.kit.geometry import RgbdFrame, invert
from octolog.mapper.fleet.align import Alignment, Features, align, features, refined, verify

REFINE_MATCHES = 5  # verified matches whose mean places a robot (the first one places it at once)
# Bounds, so that a robot that never meets the others costs the same per keyframe in minute ten as in
# minute one: the newest LIBRARY map keyframes are kept for matching (~0.5 MB of features each), and
# a new map keyframe is tried against the newest TRIES waiting keyframes of each unplaced robot.
LIBRARY = 200
TRIES = 20
# Linking again (see the module's text; how often: mapper.relink_after_m). PLACES bounds the memory
# (~1 MB of features a keyframe, its depth surface for the ICP refinement); RELINK_TRIES bounds the
# matching a keyframe costs.
RELINK_NEAR_M = 1.0
RELINK_ANGLE_DEG = 45.0
RELINK_TRIES = 2
PLACE_CELL_M = 0.5
PLACES = 100


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
    link_kinds: list[str] = field(default_factory=list)  # per link: "place", "refine" or "relink"
    relink_after_m: float = 0.0  # link placed robots again where they meet later, this far apart (0: never)
    _library: list[tuple[int, int, np.ndarray, Features]] = field(default_factory=list)  # (robot, gid, world_from_camera, f)
    _matches: dict[int, int] = field(default_factory=dict)  # robot -> verified matches that placed or refined it
    # relinking: kept keyframes by (robot, cell, direction) -> (robot, gid, world_from_camera, features),
    # oldest first; each robot's path since its last link and its last keyframe's position
    _places: dict[tuple, tuple[int, int, np.ndarray, Features]] = field(default_factory=dict)
    _since_link: dict[int, float] = field(default_factory=dict)  # metres of path
    _last_at: dict[int, np.ndarray] = field(default_factory=dict)  # each robot's last keyframe position

    @classmethod
    def known(cls, poses: list[np.ndarray]) -> Placement:
        """Every robot placed by its start pose (mapper.start_poses)."""
        return cls(len(poses), list(poses), [[] for _ in poses])

    @classmethod
    def by_place(cls, n: int, relink_after_m: float = 0.0) -> Placement:
        """Robot 0's world is the map's; the others wait to be placed; placed robots are linked again
        where they meet later, `relink_after_m` of a robot's path apart (0: never)."""
        return cls(n, [np.eye(4)] + [None] * (n - 1), [[] for _ in range(n)], relink_after_m=relink_after_m)

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
            a = verify(f, w.features)
            if a is not None and (best is None or a.inliers > best[2].inliers):
                best = (gid, world_from_cam, a, f)
        if best is None:
            return None
        gid, world_from_cam, a, f = best
        return self._place(robot, w, gid, world_from_cam, refined(f, w.features, a))

    def remember(self, robot_of: int, kf_id: int, gid: int, world_from_camera: np.ndarray,
                 frame: RgbdFrame) -> tuple[list[Merge], bool]:
        """A keyframe of robot `robot_of` (its id `kf_id`, the map's `gid`) now in the map: kept for
        matching while robots are unplaced or refined, tried against their waiting keyframes, and, if
        its robot is being refined, against the other robots' map keyframes. The merges it made
        (robots to `take`), and whether it added a link (the joint pose graph has more to settle)."""
        searching = self._searching()
        if not searching:
            self._library.clear()
            if not self.relink_after_m:
                return [], False
        f = features(frame)
        linked = self._refine(robot_of, kf_id, f) if self._refining(robot_of) else False
        if self.relink_after_m:
            at = world_from_camera[:3, 3]
            step = float(np.linalg.norm(at - self._last_at[robot_of])) if robot_of in self._last_at else 0.0
            self._last_at[robot_of] = at.copy()
            self._since_link[robot_of] = 0.0 if linked else self._since_link.get(robot_of, 0.0) + step
            if not linked and not self._refining(robot_of) and self._since_link[robot_of] >= self.relink_after_m:
                linked = self._relink(robot_of, kf_id, world_from_camera, f)
            self._keep_place(robot_of, gid, world_from_camera, f)
        if not searching:
            return [], linked
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
        robot's map keyframe; False without one, or when this keyframe placed its robot (the same
        match twice would weigh twice in the joint graph)."""
        if any(r == robot and k == kf_id for _, r, k, _ in self.links):
            return False
        best = None
        for other, gid, _, g in self._library:
            if other == robot:
                continue
            a = verify(g, f)
            if a is not None and (best is None or a.inliers > best[1].inliers):
                best = (gid, a, g)
        if best is None:
            return False
        self.links.append((best[0], robot, kf_id, refined(best[2], f, best[1])))
        self.link_kinds.append("refine")
        self._matches[robot] += 1
        return True

    def _relink(self, robot: int, kf_id: int, world_from_camera: np.ndarray, f: Features) -> bool:
        """A link for a placed robot's keyframe with the nearest kept keyframes of the other robots
        that look the same way (RELINK_TRIES at most; ties by map id); False without a verified one."""
        near = []
        cos_max = np.cos(np.radians(RELINK_ANGLE_DEG))
        for other, gid, W, g in self._places.values():
            d = float(np.linalg.norm(W[:3, 3] - world_from_camera[:3, 3]))
            if other != robot and d <= RELINK_NEAR_M and float(W[:3, 2] @ world_from_camera[:3, 2]) >= cos_max:
                near.append((d, gid, other, g))
        best = None
        for _, gid, other, g in sorted(near, key=lambda c: (c[0], c[1]))[:RELINK_TRIES]:
            a = verify(g, f)
            if a is not None and (best is None or a.inliers > best[2].inliers):
                best = (gid, other, a, g)
        if best is None:
            return False
        self.links.append((best[0], robot, kf_id, refined(best[3], f, best[2])))
        self.link_kinds.append("relink")
        self._since_link[robot] = self._since_link[best[1]] = 0.0
        if self._refining(best[1]):  # a robot placed ahead of the others refines by their relinks too
            self._matches[best[1]] += 1
        return True

    def _keep_place(self, robot: int, gid: int, world_from_camera: np.ndarray, f: Features) -> None:
        """Keep a map keyframe for linking: the newest per robot, cell and viewing direction."""
        axis = world_from_camera[:3, 2]
        k = int(np.argmax(np.abs(axis)))
        cell = tuple(int(c) for c in np.floor(world_from_camera[:3, 3] / PLACE_CELL_M))
        key = (robot, cell, k, bool(axis[k] > 0))
        self._places.pop(key, None)
        self._places[key] = (robot, gid, world_from_camera.copy(), f)
        while len(self._places) > PLACES:
            del self._places[next(iter(self._places))]

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
        self.link_kinds.append("place")
        self._matches[robot] = 1
        m = Merge(robot, w.kf_id, gid, world_from_robot, a)
        self.merges.append(m)
        return m
