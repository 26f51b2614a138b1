"""The map of several robots: the fleet merge's items (mapper/fleet/order.py) applied, one at a time.

A keyframe of a placed robot is integrated at `world_from_robot @ robot_from_camera`; an unplaced
robot's keyframe is offered to the placement (mapper/fleet/placement.py) and waits; a placed keyframe is
remembered for matching; a new link between robots lets the joint pose graph settle every placed
robot's keyframes (mapper/fleet/joint_graph.py); a correction from a robot's tracker moves its keyframes. No
transport and no clock: what goes out (merge events, map updates, Rerun) goes through `FleetHooks`,
so the same items in the same order give the same map, and the mapper can build it again from its
history in the defined order (`FleetMerge.canonical`) with no hooks at all.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from octolog.kit.errors import InputError, MapError
from octolog.kit.geometry import RgbdFrame, invert
from octolog.mapper.core import Mapper
from octolog.mapper.fleet.joint_graph import Link, joint_poses, needs_graph
from octolog.mapper.fleet.journal import Journal
from octolog.mapper.fleet.order import CorrectionItem, KeyframeItem
from octolog.mapper.fleet.placement import Merge, Placement
from octolog.schemas import posemsgs, rgbdmsgs


def _nothing(*_: object) -> None:
    return None


@dataclass
class FleetHooks:
    """What the live mapper tells the world; no-ops when the map is built again from the history."""

    merged: Callable[[Merge], None] = _nothing  # a robot placed: the merge event
    first: Callable[[np.ndarray], None] = _nothing  # before the first keyframe: robot 0's world_from_robot
    # robot, stamp, map-wide id, points, ms, frame
    integrated: Callable[[int, int, int, int, float, RgbdFrame], None] = _nothing
    refused: Callable[[int, int, float], None] = _nothing  # stamp, robot keyframe id, ms


class FleetMap:
    """The mapper, the placement and what ties them: map-wide ids, trajectories, the robots' own poses."""

    def __init__(self, mapper: Mapper, robots: tuple[str, ...], placement: Placement,
                 hooks: FleetHooks | None = None, journal: Journal | None = None) -> None:
        """`journal`: where every call on the map is written down for shards that follow this
        mapper's placement (mapper/fleet/journal.py)."""
        n = len(robots)
        self.mapper, self.robots, self.placement = mapper, robots, placement
        self.hooks = hooks or FleetHooks()
        self.journal = journal
        self.map_id: list[dict[int, int]] = [{} for _ in range(n)]  # robot keyframe id -> map-wide id
        self.trajectories: list[list[tuple[int, int]]] = [[] for _ in range(n)]  # (stamp, map-wide id)
        self.robot_pose: list[dict[int, np.ndarray]] = [{} for _ in range(n)]  # map-wide id -> robot_from_camera
        self.keyframes = self.skipped = self.corrections = 0
        self.ms: list[float] = []
        self.problems: list[str] = []

    def apply(self, i: int, item: KeyframeItem | CorrectionItem) -> None:
        """One item of robot `i`, as the merge gave it."""
        if isinstance(item, CorrectionItem):
            self._correct(i, item)
        else:
            self._keyframe(i, item)

    def settle(self) -> int | None:
        """With more links between robots than placing them took, one pose graph over every placed
        robot's keyframes (mapper/fleet/joint_graph.py) moves them; later keyframes follow their robot's newest.
        Returns how many keyframes moved; None without a graph to solve."""
        p = self.placement
        links = [Link(a, self.map_id[r][k], al.a_from_b, al.rmse_m) for a, r, k, al in p.links if k in self.map_id[r]]
        if not needs_graph(links, sum(W is not None for W in p.world_from_robot)):
            return None
        poses = joint_poses(self.robot_pose, p.world_from_robot, links)
        for r, mine in enumerate(self.robot_pose):
            if mine and p.world_from_robot[r] is not None:
                last = max(mine)
                p.world_from_robot[r] = poses[last] @ invert(mine[last])
        return self._move(poses)

    def _move(self, poses: dict[int, np.ndarray]) -> int:
        """`Mapper.correct`, written down once it is taken."""
        moved = self.mapper.correct(poses)
        if self.journal is not None:
            self.journal.corrected(poses)
        return moved

    def _correct(self, i: int, item: CorrectionItem) -> None:
        try:
            poses = posemsgs.keyframe_poses_from_msg(item.poses)
            W = self.placement.world_from_robot[i]
            if W is None:  # not in the map yet: its waiting keyframes move
                self.placement.correct(i, poses)
                return
            mine = self.map_id[i]
            ids, offset = [mine[k] for k in poses if k in mine], float(item.poses.depth_inverse_offset)
            recorrected = self.mapper.recorrect_depth(ids, offset)
            if self.journal is not None and recorrected:
                self.journal.recorrected(ids, offset)
            self.robot_pose[i].update({mine[k]: T for k, T in poses.items() if k in mine})
            moved = self.settle()  # with links: the joint graph, from the robot's corrected poses
            if moved is None:
                moved = self._move({mine[k]: W @ T for k, T in poses.items() if k in mine})
            self.corrections += max(moved, len(recorrected))
        except InputError as exc:  # the whole correction is refused; the map is unchanged
            self.problems.append(f"{self.robots[i]}: {exc}")

    def _keyframe(self, i: int, item: KeyframeItem) -> None:
        t0 = time.perf_counter()
        try:
            if item.kf_id in self.map_id[i]:
                raise InputError(f"keyframe {item.kf_id}: already integrated")
            kf_id, pose, frame = rgbdmsgs.keyframe_from_msg(item.payload)
        except InputError as exc:
            self.skipped += 1
            self.problems.append(f"{self.robots[i]}: {exc}")
            self.hooks.refused(item.stamp_ns, item.kf_id, (time.perf_counter() - t0) * 1e3)
            return
        todo = [(i, kf_id, item.stamp_ns, pose, frame)]
        p = self.placement
        if not p.placed(i):
            merge = p.offer(i, kf_id, item.stamp_ns, pose, frame)
            todo = [] if merge is None else self._placed(merge)
        if todo and not self.mapper.keyframes:  # `map` before the first keyframe
            self.hooks.first(p.world_from_robot[0])
        while todo:
            r, kid, stamp, pose, frame = todo.pop(0)
            gid = len(self.mapper.keyframes)
            world_from_camera = p.world_from_robot[r] @ pose
            try:
                pts = self.mapper.integrate(gid, world_from_camera, frame)
            except (InputError, MapError) as exc:  # one update per keyframe taken (mapper/end's count)
                self.skipped += 1
                self.problems.append(f"{self.robots[r]}: {exc}")
                self.hooks.refused(stamp, kid, (time.perf_counter() - t0) * 1e3)
                t0 = time.perf_counter()
                continue
            if self.journal is not None:
                self.journal.integrated(r, kid, gid, world_from_camera, frame)
            self.map_id[r][kid] = gid
            self.trajectories[r].append((stamp, gid))
            self.keyframes += 1
            self.robot_pose[r][gid] = pose
            merges, linked = p.remember(r, kid, gid, self.mapper.keyframes[gid].world_from_camera, frame)
            for m in merges:
                todo += self._placed(m)
            if linked:  # one more match between robots: the joint graph settles the keyframes
                self.corrections += self.settle() or 0
            ms = (time.perf_counter() - t0) * 1e3
            t0 = time.perf_counter()
            self.ms.append(ms)
            self.hooks.integrated(r, stamp, gid, pts, ms, frame)

    def _placed(self, m: Merge) -> list[tuple[int, int, int, np.ndarray, RgbdFrame]]:
        """A robot just placed: the merge announced, and its waiting keyframes to integrate, in order."""
        self.hooks.merged(m)
        return [(m.robot, w.kf_id, w.stamp_ns, w.robot_from_camera, w.frame) for w in self.placement.take(m.robot)]
