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
network: the same streams give the same map, byte for byte. The price is that a robot with no new
keyframe holds the others back until it sends one or ends its stream (see docs/deployment.md).
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


class FleetMerge:
    """Per-robot FIFOs and the merge rule above. Pure: no transport, no clock."""

    def __init__(self, robots: tuple[str, ...]) -> None:
        self.robots = robots
        self._streams = [_Stream() for _ in robots]

    def push(self, robot: int, item: KeyframeItem | CorrectionItem) -> None:
        """Append an item to robot `robot`'s stream, in the order its tracker sent it."""
        self._streams[robot].items.append(item)

    def end(self, robot: int) -> None:
        """No more items from this robot (its stream end arrived and the count is complete)."""
        self._streams[robot].ended = True

    def waiting_on(self) -> list[int]:
        """Robots whose next item is needed before anything can be decided."""
        return [i for i, s in enumerate(self._streams) if not s.items and not s.ended]

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
        for i, item in heads:
            if isinstance(item, CorrectionItem):
                return i, self._streams[i].items.popleft()
        i, _ = min(heads, key=lambda h: (h[1].stamp_ns, h[0], h[1].kf_id))
        return i, self._streams[i].items.popleft()


def merged_order(streams: list[list[KeyframeItem]]) -> list[tuple[int, KeyframeItem]]:
    """The integration order of complete keyframe-only streams (what `FleetMerge` yields for them)."""
    merge = FleetMerge(tuple(str(i) for i in range(len(streams))))
    for i, items in enumerate(streams):
        for item in items:
            merge.push(i, item)
        merge.end(i)
    out = []
    while (nxt := merge.pop()) is not None:
        out.append(nxt)  # type: ignore[arg-type]
    return out
