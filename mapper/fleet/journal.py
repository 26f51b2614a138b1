"""One placement authority for a sharded fleet map: the placing mapper's journal, and following it.

A fleet's placement (mapper/fleet/placement.py) and joint graph decide where every robot's keyframes
go; the shards of one map must decide the same. One mapper places (the `placement` stage in its
namespace); it writes down every call it makes on its map, in order: a keyframe integrated (which
robot's keyframe, at which pose, under which map-wide id), keyframes moved, depth re-corrected, the
map frame's up, the map cleared to be built again in the defined order. Those calls are the whole
of what placement, corrections and the merge order did to the map: a mapper that makes the same calls
on the same keyframes builds the same map, byte for byte, without matching a single place itself.

The journal goes out on `mapper/placed` (one JSON object per sample, in order) and into the placing
mapper's folder as `placed.jsonl` when it ends. A follower (`mapper.follow`) applies it live from
the bus, or from that file to build a shard again from the robots' logs: the same bytes as the
first time, whatever the timing of either run.

Floats are written with Python's shortest round-trip repr, so the poses a follower applies are the
bits the placing mapper applied.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.files import write_bytes_atomic
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.mapper.core import FrameRef, Mapper, reaches

__all__ = ["JOURNAL_FILE", "Journal", "apply_op", "read_journal"]

JOURNAL_FILE = "placed.jsonl"
FORMAT = "octolog-placement-journal"
VERSION = 1


def _matrix(T: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(T, dtype=np.float64).reshape(16)]


def _pose(values: list[float]) -> np.ndarray:
    T = np.array(values, dtype=np.float64)
    if T.shape != (16,) or not np.isfinite(T).all():
        raise InputError("placement journal: a pose that is not 16 finite numbers")
    return T.reshape(4, 4)


class Journal:
    """The placing mapper's calls on its map as they happen; `emit` gets each op's JSON line.

    With `route` (a shard), each keyframe goes to the other shards whose tiles it can reach
    (`route(shard, robot, kf)`, before the op that needs it), once per shard: at its integration,
    and when a correction, a depth re-correction or a new map frame brings it within their reach."""

    def __init__(self, mapper: Mapper, robots: tuple[str, ...], emit: Callable[[str], None],
                 found: Callable[[], dict | None] = lambda: None,
                 route: Callable[[int, int, int], None] | None = None) -> None:
        self.mapper, self.robots, self.emit, self.found, self.route = mapper, robots, emit, found, route
        self.lines: list[str] = []
        self._up: list[float] | None = None
        own = mapper.params.tiles
        self._others = [] if own is None or route is None else \
            [dataclasses.replace(own, index=k) for k in range(1, own.count + 1) if k != own.index]
        self._source: dict[int, tuple[int, int, Intrinsics]] = {}  # gid -> robot, keyframe id, camera
        self.sent: set[tuple[int, int]] = set()  # (shard, gid) routed

    def _put(self, op: dict[str, object], gids: Iterable[int] = ()) -> None:
        if not self.lines:
            self._write({"op": "start", "format": FORMAT, "version": VERSION, "robots": list(self.robots)})
        up = [float(v) for v in self.mapper.params.grid.up]
        if up != self._up:  # the map frame first: a follower builds in it too
            self._up = up
            self._route(list(self._source))
            self._write({"op": "up", "up": up, "found": self.found()})
        self._route(gids)
        self._write(op)

    def _route(self, gids: Iterable[int]) -> None:
        """Send each keyframe to the shards it now reaches and has not been sent to."""
        c = self.mapper.params.cloud
        for gid in gids:
            kf = self.mapper.keyframes.get(gid)
            if kf is None or gid not in self._source:
                continue
            robot, kf_id, camera = self._source[gid]
            map_from_camera = self.mapper.map_from_world @ kf.world_from_camera
            for tiles in self._others:
                if (tiles.index, gid) not in self.sent and reaches(tiles, map_from_camera, camera, kf.inverse_offset,
                                                                   c.max_range_m, self.mapper.resolution_m):
                    self.sent.add((tiles.index, gid))
                    self.route(tiles.index, robot, kf_id)  # type: ignore[misc]

    def _write(self, op: dict[str, object]) -> None:
        line = json.dumps(op, sort_keys=True)
        self.lines.append(line)
        self.emit(line)

    def integrated(self, robot: int, kf_id: int, gid: int, world_from_camera: np.ndarray, frame: RgbdFrame) -> None:
        K = frame.intrinsics
        self._source[gid] = (robot, kf_id, K)
        self._put({"op": "integrate", "robot": robot, "kf": kf_id, "stamp": frame.stamp_ns, "gid": gid,
                   "pose": _matrix(world_from_camera), "seq": frame.seq,
                   "camera": [K.width, K.height, K.fx, K.fy, K.cx, K.cy],
                   "inverse_offset": float(frame.depth_inverse_offset)}, [gid])

    def corrected(self, poses: dict[int, np.ndarray]) -> None:
        self._put({"op": "correct", "poses": [[gid, _matrix(T)] for gid, T in poses.items()]}, list(poses))

    def recorrected(self, ids: list[int], inverse_offset: float) -> None:
        self._put({"op": "recorrect", "ids": list(ids), "offset": float(inverse_offset)}, ids)

    def cleared(self) -> None:
        self._put({"op": "clear"})

    def end(self, summary: dict[str, object]) -> None:
        """The last op: what the placing mapper reports (merges, links, robots lost and unplaced)."""
        self._put({"op": "end", **summary})

    def write(self, out_dir: Path) -> Path:
        """`out_dir/placed.jsonl`, whole or not at all."""
        path = out_dir / JOURNAL_FILE
        write_bytes_atomic(path, ("\n".join(self.lines) + "\n").encode())
        return path


def read_journal(where: Path) -> list[dict[str, Any]]:
    """The ops of a placing mapper's `placed.jsonl` (its folder or the file); InputError when it is
    missing, damaged or ends without its end op (its mapper did not finish)."""
    path = where / JOURNAL_FILE if where.is_dir() else where
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"{path}: no placement journal ({exc.strerror or exc}; the placing mapper writes "
                         f"{JOURNAL_FILE} into its --out folder when it finishes)") from None
    try:
        ops = [json.loads(line) for line in text.splitlines() if line.strip()]
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: damaged placement journal (line {exc.lineno}: {exc.msg})") from None
    if not ops or ops[0].get("format") != FORMAT or ops[0].get("version") != VERSION:
        raise InputError(f"{path}: not a version-{VERSION} octolog placement journal")
    if ops[-1].get("op") != "end":
        raise InputError(f"{path}: the placement journal ends early (its mapper did not finish)")
    return ops


def apply_op(mapper: Mapper, op: dict[str, Any], frame_of: Callable[[int, int], RgbdFrame]) -> int | None:
    """One journal op on a follower's map; for an integrate, the map-wide id (InputError/MapError if
    the follower's mapper refuses the keyframe: the caller's to report). `frame_of(robot, kf)` gives
    a robot's keyframe frame; it is asked only when the follower makes the keyframe's cloud (it
    reaches the follower's tiles). Keyframes the follower does not hold are skipped by the moving
    ops, as `Mapper.correct` skips unknown ids."""
    kind = op["op"]
    if kind == "integrate":
        robot, kf_id, gid = int(op["robot"]), int(op["kf"]), int(op["gid"])
        w, h, fx, fy, cx, cy = op["camera"]
        ref = FrameRef(int(op["stamp"]), int(op["seq"]), Intrinsics(int(w), int(h), float(fx), float(fy), float(cx),
                                                                     float(cy)),
                       float(op["inverse_offset"]), lambda: frame_of(robot, kf_id))
        mapper.integrate(gid, _pose(op["pose"]), ref)  # the frame is fetched if its cloud is made
        return gid
    if kind == "correct":
        mapper.correct({int(gid): _pose(T) for gid, T in op["poses"]})
    elif kind == "recorrect":
        mapper.recorrect_depth([int(i) for i in op["ids"] if int(i) in mapper.keyframes], float(op["offset"]))
    elif kind == "clear":
        mapper.clear()
    elif kind == "up":
        pass  # the caller's MapFrame applies it (and announces the frame)
    elif kind not in ("start", "end"):
        raise InputError(f"placement journal: unknown op {kind!r}")
    return None
