"""Several robots into one map: the deterministic merge of per-robot keyframe streams.

Each robot (a replay/recorder + tracker pair under its own namespace) has its own world: its
tracker's first camera frame. The mapper config gives each robot's start pose in the common world
(`world_from_<robot>`), so a keyframe pose becomes `world_from_robot @ robot_from_camera`.

The octree update is order dependent (clamped log-odds), so the integration order is defined, not
left to arrival timing: every item (keyframe or pose correction) carries its sensor stamp (a
correction, the stamp of the frame its tracker applied it at), and the merge takes the items of all
robots sorted by (stamp, robot index), each robot's in the order its tracker sent them:

1. every robot's stream (keyframes, pose corrections and watermarks, in the order its tracker sent
   them) is a FIFO; the merge decides only when every robot that has not ended has something waiting;
2. the head with the smallest (sensor stamp, robot index) is taken.

A watermark (`Watermark`, from the tracker's status of each frame it processed) says "nothing older
than this stamp will come from me": it is a head like an item, sorts before a robot's items of the
same stamp, and is dropped when taken. It carries no data, so the items' order is the same with or
without watermarks, wherever they fall: they only let the merge decide sooner. A robot that tracks
without making keyframes therefore holds the others back by no more than the bus's latency.

The decision depends only on the streams' contents, never on which message came first over the
network: the same streams give the same map, byte for byte. A robot that sends nothing at all (its
camera stopped; its tracker alive) holds the others back until it sends something or ends its
stream, or until the mapper pauses it (`pause`, after `mapper.robot_stall_s` of silence): then the
others go on without it, its later items join the merge when they come (late, out of the defined
order), and the merge says it `jumped`. Every item is kept (`history`), so the mapper can then
build the map again in the defined order (`canonical`): the final map is the one the order
defines, whatever the timing was. Keyframes get map-wide ids 0, 1, 2, ... in integration order.
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
    """A robot's pose correction waiting in its stream."""

    stamp_ns: int  # the frame its tracker applied it at (the message's header stamp)
    poses: Any  # the robot's {kf_id: robot_from_camera}, or whatever the caller stores


@dataclass(frozen=True)
class Watermark:
    """A robot's promise that nothing older than `stamp_ns` will come from it (its tracker has
    processed the frame of that stamp): lets the merge decide without waiting for its next item."""

    stamp_ns: int


Item = KeyframeItem | CorrectionItem


def _order(head: tuple[int, Item | Watermark]) -> tuple[int, int]:
    i, item = head
    return (item.stamp_ns, -1 if isinstance(item, Watermark) else i)


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

    def push(self, robot: int, item: Item | Watermark) -> None:
        """Append an item to robot `robot`'s stream, in the order its tracker sent it. Watermarks
        in a row collapse to the newest; after the stream's end they are ignored."""
        s = self._streams[robot]
        s.paused = False
        if isinstance(item, Watermark):
            if s.ended:
                return
            if s.items and isinstance(s.items[-1], Watermark):
                s.items[-1] = max(s.items[-1], item, key=lambda w: w.stamp_ns)
                return
        else:
            s.history.append(item)
        s.items.append(item)

    def pause(self, robot: int) -> None:
        """Stop waiting for robot `robot` until its next item (it is silent, not gone)."""
        self._streams[robot].paused = True

    def paused(self) -> list[int]:
        """Robots paused with nothing waiting (not ended)."""
        return [i for i, s in enumerate(self._streams) if s.paused and not s.items and not s.ended]

    def end(self, robot: int) -> None:
        """No more items from this robot (its stream end arrived and the count is complete)."""
        s = self._streams[robot]
        s.ended = True
        s.items = deque(it for it in s.items if not isinstance(it, Watermark))

    def waiting_on(self) -> list[int]:
        """Robots whose next item is needed before anything can be decided."""
        return [i for i, s in enumerate(self._streams) if not s.items and not s.ended and not s.paused]

    def has_items(self, robot: int) -> bool:
        """Whether robot `robot` has items (keyframes, corrections) waiting."""
        return any(not isinstance(it, Watermark) for it in self._streams[robot].items)

    def done(self) -> bool:
        """Every stream has ended and been drained."""
        return all(s.ended and not s.items for s in self._streams)

    def pop(self) -> tuple[int, Item] | None:
        """The next (robot index, item) in the defined order, or None while the order is not decided."""
        while not self.waiting_on():
            heads = [(i, s.items[0]) for i, s in enumerate(self._streams) if s.items]
            if not heads:
                return None
            i, item = min(heads, key=_order)
            self._streams[i].items.popleft()
            if isinstance(item, Watermark):
                continue  # robot i's next item is newer than everything taken so far
            self.jumped = self.jumped or bool(self.paused())
            return i, item
        return None

    def canonical(self) -> list[tuple[int, Item]]:
        """Every item pushed so far, in the defined order (as if every stream had been complete
        from the start): the order the map is built in again after a pause let the merge jump."""
        return merged_order([s.history for s in self._streams])


def merged_order(streams: list[list]) -> list[tuple[int, Item]]:
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
