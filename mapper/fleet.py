"""Several robots into one map: the deterministic merge of per-robot keyframe streams.

Each robot (a replay/recorder + tracker pair under its own namespace) has its own world: its
tracker's first camera frame. The mapper config gives each robot's start pose in the common world
(`world_from_<robot>`), so a keyframe pose becomes `world_from_robot @ robot_from_camera`.

The octree update is order dependent (clamped log-odds), so the integration order is defined, not
left to arrival timing:

1. every robot's stream (keyframes and pose corrections, in the order its tracker sent them) is a
   FIFO; the merge decides only when every robot that has not ended has at least one item waiting;
2. a pose correction at the head of a stream is applied first (lowest robot index first);
3. otherwise the keyframe with the smallest (sensor stamp, robot index, keyframe id) is integrated.

The decision depends only on the streams' contents, never on which message came first over the
network: the same streams give the same map, byte for byte. A robot with no new keyframe holds the
others back until it sends one or ends its stream, or until the mapper pauses it (`pause`, after
`mapper.robot_stall_s` of silence): then the others go on without it, its later items join the
merge when they come (late, out of the defined order), and the merge says it `jumped`. Every item
is kept (`history`), so the mapper can then build the map again in the defined order
(`canonical`): the final map is the one the order defines, whatever the timing was.
Keyframes get map-wide ids 0, 1, 2, ... in integration order.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from octolog.kit.errors import ConfigError
from octolog.kit.geometry import pose_to_matrix


def start_pose_matrix(robot: str, xyz_qxyzw: tuple[float, ...]) -> np.ndarray:
    """`world_from_<robot>` from x y z qx qy qz qw (metres; quaternion normalised here)."""
    v = np.asarray(xyz_qxyzw, dtype=np.float64)
    if v.shape != (7,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"mapper.start_poses for {robot!r}: want 7 finite numbers x y z qx qy qz qw, "
                          f"got {list(xyz_qxyzw)}")
    if not np.linalg.norm(v[3:]) > 1e-9:
        raise ConfigError(f"mapper.start_poses for {robot!r}: the quaternion is zero")
    return pose_to_matrix(v[:3], v[3:] / np.linalg.norm(v[3:]))


@dataclass(frozen=True)
class KeyframeItem:
    """A robot's keyframe waiting in its stream, with what the merge orders it by."""

    stamp_ns: int
    kf_id: int  # the robot's own keyframe id
    payload: Any  # whatever the caller needs to integrate it (decoded message, frame, ...)


@dataclass(frozen=True)
class CorrectionItem:
    """A robot's pose correction waiting in its stream (applied before any keyframe)."""

    poses: Any  # the robot's {kf_id: robot_from_camera}, or whatever the caller stores


@dataclass
class _Stream:
    items: deque = field(default_factory=deque)
    ended: bool = False
    paused: bool = False  # silent too long: not waited for until its next item
    history: list = field(default_factory=list)  # every item pushed, in order


class FleetMerge:
    """Per-robot FIFOs and the merge rule above. Pure: no transport, no clock."""

    def __init__(self, robots: tuple[str, ...]) -> None:
        self.robots = robots
        self._streams = [_Stream() for _ in robots]
        self.jumped = False  # an item was taken while a paused robot had nothing waiting

    def push(self, robot: int, item: KeyframeItem | CorrectionItem) -> None:
        """Append an item to robot `robot`'s stream, in the order its tracker sent it."""
        s = self._streams[robot]
        s.items.append(item)
        s.history.append(item)
        s.paused = False

    def pause(self, robot: int) -> None:
        """Stop waiting for robot `robot` until its next item (it is silent, not gone)."""
        self._streams[robot].paused = True

    def paused(self) -> list[int]:
        """Robots paused with nothing waiting (not ended)."""
        return [i for i, s in enumerate(self._streams) if s.paused and not s.items and not s.ended]

    def end(self, robot: int) -> None:
        """No more items from this robot (its stream end arrived and the count is complete)."""
        self._streams[robot].ended = True

    def waiting_on(self) -> list[int]:
        """Robots whose next item is needed before anything can be decided."""
        return [i for i, s in enumerate(self._streams) if not s.items and not s.ended and not s.paused]

    def has_items(self, robot: int) -> bool:
        """Whether robot `robot` has items waiting."""
        return bool(self._streams[robot].items)

    def done(self) -> bool:
        """Every stream has ended and been drained."""
        return all(s.ended and not s.items for s in self._streams)

    def pop(self) -> tuple[int, KeyframeItem | CorrectionItem] | None:
        """The next (robot index, item) in the defined order, or None while the order is not decided."""
        if self.waiting_on():
            return None
        heads = [(i, s.items[0]) for i, s in enumerate(self._streams) if s.items]
        if not heads:
            return None
        self.jumped = self.jumped or bool(self.paused())
        for i, item in heads:
            if isinstance(item, CorrectionItem):
                return i, self._streams[i].items.popleft()
        i, _ = min(heads, key=lambda h: (h[1].stamp_ns, h[0], h[1].kf_id))
        return i, self._streams[i].items.popleft()

    def canonical(self) -> list[tuple[int, KeyframeItem | CorrectionItem]]:
        """Every item pushed so far, in the defined order (as if every stream had been complete
        from the start): the order the map is built in again after a pause let the merge jump."""
        return merged_order([s.history for s in self._streams])


def merged_order(streams: list[list]) -> list[tuple[int, KeyframeItem | CorrectionItem]]:
    """The order `FleetMerge` yields complete streams (keyframes and corrections) in."""
    merge = FleetMerge(tuple(str(i) for i in range(len(streams))))
    for i, items in enumerate(streams):
        for item in items:
            merge.push(i, item)
        merge.end(i)
    out = []
    while (nxt := merge.pop()) is not None:
        out.append(nxt)
    return out
