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

import json
from pathlib import Path
from typing import Any, Callable

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.files import write_bytes_atomic
from octolog.kit.geometry import RgbdFrame
from octolog.mapper.core import Mapper

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
    """The placing mapper's calls on its map as they happen; `emit` gets each op's JSON line."""

    def __init__(self, mapper: Mapper, robots: tuple[str, ...], emit: Callable[[str], None],
                 found: Callable[[], dict | None] = lambda: None) -> None:
        self.mapper, self.robots, self.emit, self.found = mapper, robots, emit, found
        self.lines: list[str] = []
        self._up: list[float] | None = None

    def _put(self, op: dict[str, Any]) -> None:
        if not self.lines:
            self._write({"op": "start", "format": FORMAT, "version": VERSION, "robots": list(self.robots)})
        up = [float(v) for v in self.mapper.params.grid.up]
        if up != self._up:  # the map frame first: a follower builds in it too
            self._up = up
            self._write({"op": "up", "up": up, "found": self.found()})
        self._write(op)

    def _write(self, op: dict[str, Any]) -> None:
        line = json.dumps(op, sort_keys=True)
        self.lines.append(line)
        self.emit(line)

    def integrated(self, robot: int, kf_id: int, stamp_ns: int, gid: int, world_from_camera: np.ndarray) -> None:
        self._put({"op": "integrate", "robot": robot, "kf": kf_id, "stamp": stamp_ns, "gid": gid,
                   "pose": _matrix(world_from_camera)})

    def corrected(self, poses: dict[int, np.ndarray]) -> None:
        self._put({"op": "correct", "poses": [[gid, _matrix(T)] for gid, T in poses.items()]})

    def recorrected(self, ids: list[int], inverse_offset: float) -> None:
        self._put({"op": "recorrect", "ids": list(ids), "offset": float(inverse_offset)})

    def cleared(self) -> None:
        self._put({"op": "clear"})

    def end(self, summary: dict[str, Any]) -> None:
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
    """One journal op on a follower's map; for an integrate, the map-wide id (None if the follower's
    mapper refused the keyframe: InputError/MapError are the caller's to report). `frame_of(robot,
    kf)` gives a robot's keyframe frame. Keyframes the follower does not hold are skipped by the
    moving ops, as `Mapper.correct` skips unknown ids."""
    kind = op["op"]
    if kind == "integrate":
        frame = frame_of(int(op["robot"]), int(op["kf"]))
        gid = int(op["gid"])
        mapper.integrate(gid, _pose(op["pose"]), frame)
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
