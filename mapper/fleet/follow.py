"""A fleet mapper that follows another's placement (`mapper.follow`): the shards of one map after
their placement authority.

It places nothing and merges nothing: the placing mapper's journal (mapper/fleet/journal.py), live
from the bus or from its `placed.jsonl`, says which keyframe goes into the map at which pose under
which id, and which keyframes move. The robots' corrections and statuses are not even subscribed
to: their effect on the map is in the journal. So a follower costs no place matching, and it builds
the map the placing mapper would have built with its tiles, whatever the timing of either.

Live, a shard takes no keyframe from the robots: the placing mapper routes each keyframe to the
shards whose tiles it reaches, on `mapper/route/<shard>/<robot>` in its namespace (Zenoh delivers
a key only where it is subscribed), and sends it again when a correction brings it within reach of
another shard. The follower's map asks for a keyframe's frame only when it makes its cloud (a
`FrameRef` until then), so the keyframes that never reach its tiles never cross the network to it.
Built again from a journal file, a follower takes the keyframes from the robots' logs instead.

A follower cannot go on without its authority: if the placing mapper is gone before its journal
ends, the follower says so in one line and writes no map (its tiles are missing, never wrong).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from collections import deque
from pathlib import Path
from typing import Any, Iterator

from octolog.kit.bus import Bus, BusConfig, Publisher, Received
from octolog.kit.config import to_dict
from octolog.kit.errors import InputError, MapError, StageError
from octolog.kit.geometry import RgbdFrame
from octolog.kit.viz import Viz
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import Mapper, make_mapper
from octolog.mapper.fleet.journal import apply_op, read_journal
from octolog.mapper.fleet.node import ROBOT_INBOX, write_trajectories
from octolog.mapper.mapframe import MapFrame
from octolog.mapper.process import (
    INBOX_KEYFRAMES,
    MapperResult,
    MapSnapshots,
    answer_save,
    finish,
    log_map,
    publish_update,
)
from octolog.schemas import rgbdmsgs, streammsgs
from octolog.schemas.msgtypes import CompressedKeyframeMsg, KeyframeMsg
from octolog.schemas.topics import (
    CONFIGS,
    KEYFRAME,
    KEYFRAME_COMPRESSED,
    KEYFRAME_END,
    MAP_PLACED,
    MAP_SAVE,
    MAP_UPDATE,
    route_topic,
)

JOURNAL_PREFIX = "journal:"
PLACEMENT_STAGE = "placement"  # the stage the placing mapper announces in its namespace


def run_follower(cfg: MapperConfig, bus_cfg: BusConfig, *, out_dir: Path, rerun: str = "off",
                 recording_id: str = "octolog") -> MapperResult:
    """Build the map of `cfg.robots` by the journal of the mapper `cfg.follow` names: a namespace
    (live, its stage `placement`; a shard gets from it the keyframes that reach its tiles) or
    `journal:PATH` (its folder or its placed.jsonl; the keyframes from the robots)."""
    mapper = make_mapper(cfg)
    recorded = read_journal(Path(cfg.follow[len(JOURNAL_PREFIX):])) if cfg.follow.startswith(JOURNAL_PREFIX) else None
    if recorded is not None and recorded[0]["robots"] != list(cfg.robots):
        raise InputError(f"mapper.follow {cfg.follow}: its robots are {recorded[0]['robots']}, "
                         f"mapper.robots {list(cfg.robots)}")
    # a live shard is routed to: its keyframes come from the placing mapper
    shard = cfg.tiles().index if cfg.shard and recorded is None else None
    with contextlib.ExitStack() as stack:
        bus = stack.enter_context(Bus(bus_cfg, cfg.stage, inbox_size=INBOX_KEYFRAMES))
        leader = None if recorded is not None else LeaderStream(stack.enter_context(
            Bus(dataclasses.replace(bus_cfg, namespace=cfg.follow), cfg.stage, inbox_size=ROBOT_INBOX)),
            cfg.follow, len(cfg.robots), shard)
        robot_buses = [stack.enter_context(Bus(dataclasses.replace(bus_cfg, namespace=r), cfg.stage,
                                               inbox_size=ROBOT_INBOX)) for r in cfg.robots]
        viz = stack.enter_context(Viz(rerun, "mapper", recording_id))
        frame = MapFrame(mapper, bus, viz, from_imu=False)  # the authority's up comes in its journal
        publisher = MapSnapshots(bus, mapper, cfg.publish_every)
        bus.accept(MAP_SAVE)
        bus.start([])
        bus.publisher(CONFIGS["mapper"]).put(streammsgs.config_msg("mapper", to_dict(cfg)))
        if leader is not None:  # subscribed before the robots hear of this mapper: nothing is missed
            leader.start(cfg.wait_timeout_s)
        for rb in robot_buses:  # ready for the robot's keyframes, from the robot or routed by the leader
            rb.start([] if shard else [KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_END], wait_for=cfg.wait_for,
                     timeout_s=cfg.wait_timeout_s)
            if not shard:
                rb.watch(["tracker"])
        frames: LeaderStream | RobotFrames = \
            leader if shard else RobotFrames(cfg.robots, robot_buses)  # type: ignore[assignment]
        ops = iter(recorded) if leader is None else leader.journal()
        follow = Follower(mapper, cfg, frame, frames)
        follow.run(ops, bus, viz, publisher, out_dir)
        result = follow.result()
        per_robot = write_trajectories(mapper, cfg.robots, follow.trajectories, out_dir)
        for robot in per_robot:
            per_robot[robot]["merged"] = robot not in result.unmerged
            per_robot[robot]["lost"] = robot in result.lost
        stats = {"robots": per_robot, "merges": result.merges, "links": result.links, "followed": cfg.follow,
                 "keyframes_received": frames.count, **({"map_frame": frame.found} if frame.found else {})}
        finish(mapper, result, bus, viz, publisher, out_dir, stats)
    return result


class LeaderStream:
    """What the placing mapper sends a follower from its namespace: its journal's ops and, for a
    shard, the robots' keyframes that reach the shard's tiles (`route_topic`)."""

    def __init__(self, bus: Bus, namespace: str, robots: int, shard: int | None) -> None:
        self.bus, self.namespace, self.robots, self.shard = bus, namespace, robots, shard
        self.ops: deque[dict[str, Any]] = deque()
        self.kept: list[dict[int, KeyframeMsg | CompressedKeyframeMsg]] = [{} for _ in range(robots)]
        self.ended = False
        self.read = 0  # journal ops
        self.count = 0  # keyframes routed here

    def start(self, timeout_s: float) -> None:
        routes = [route_topic(self.shard, r, c) for r in range(self.robots) for c in (False, True)] \
            if self.shard else []
        self.bus.start([MAP_PLACED, *routes], wait_for=[PLACEMENT_STAGE], timeout_s=timeout_s)

    def _read(self) -> bool:
        """One message in (an op, or a keyframe); False if none came within the bus's wait."""
        try:
            r = self.bus.receive()
        except StageError as exc:
            raise StageError(f"mapper: the placing mapper in {self.namespace} is gone after {self.read} journal ops "
                             f"({exc}): this mapper cannot place the robots itself, so it writes no map (run the "
                             f"placing mapper again, then this one with follow=journal:ITS_FOLDER)") from None
        if r is None:
            return False
        msg = r.decode()
        if r.topic == MAP_PLACED:
            try:
                op = json.loads(msg.data)
            except json.JSONDecodeError:
                raise StageError(f"mapper: a malformed journal op from the placing mapper in "
                                 f"{self.namespace}") from None
            self.ops.append(op)
            self.read += 1
            if op.get("op") == "end":
                self.ended = True
                self.bus.unwatch(PLACEMENT_STAGE)
        else:  # mapper/route/<shard>/<robot>[/compressed]
            self.kept[int(r.topic.name.split("/")[3])][int(msg.id)] = msg
            self.count += 1
        return True

    def journal(self) -> Iterator[dict[str, Any]]:
        """The ops in order, as they come."""
        while True:
            while not self.ops:
                self._read()
            op = self.ops.popleft()
            yield op
            if op.get("op") == "end":
                return

    def frame(self, robot: int, kf_id: int) -> RgbdFrame:
        """A keyframe routed here, waiting for it; StageError if it was not."""
        while kf_id not in self.kept[robot]:
            if not self._read() and self.ended:
                raise StageError(f"mapper: keyframe {kf_id} of robot {robot + 1} reaches this shard's tiles but the "
                                 f"placing mapper in {self.namespace} did not route it here")
        return rgbdmsgs.keyframe_from_msg(self.kept[robot][kf_id])[2]


class RobotFrames:
    """Every robot's keyframes as they arrive, kept by (robot, keyframe id): the journal names them
    (again, when the map is built anew in the defined order)."""

    def __init__(self, robots: tuple[str, ...], robot_buses: list[Bus]) -> None:
        self.robots, self.robot_buses = robots, robot_buses
        self.kept: list[dict[int, KeyframeMsg | CompressedKeyframeMsg]] = [{} for _ in robots]
        self.expected: list[int | None] = [None] * len(robots)
        self.received = [0] * len(robots)

    @property
    def count(self) -> int:
        """Keyframes received."""
        return sum(self.received)

    def _push(self, k: int, r: Received) -> None:
        if r.topic == KEYFRAME_END:
            end = r.decode()
            if end.topic in (KEYFRAME.name, KEYFRAME_COMPRESSED.name):
                self.expected[k] = int(end.count)
                self.robot_buses[k].expect_count(KEYFRAME, self.received[k], int(end.count))
                self.robot_buses[k].unwatch("tracker")
            return
        msg = r.decode()
        self.received[k] += 1
        self.kept[k][int(msg.id)] = msg

    def frame(self, robot: int, kf_id: int) -> RgbdFrame:
        """Robot `robot`'s keyframe `kf_id`, waiting for it; StageError if it cannot come."""
        name, rb = self.robots[robot], self.robot_buses[robot]
        while kf_id not in self.kept[robot]:
            if self.expected[robot] is not None and self.received[robot] >= self.expected[robot]:
                raise StageError(f"mapper: {name}'s keyframe {kf_id} is in the placing mapper's journal but not in "
                                 f"{name}'s stream (it ended with {self.received[robot]})")
            try:
                r = rb.receive()
                if r is None and self.expected[robot] is not None:
                    rb.expect_count(KEYFRAME, self.received[robot], self.expected[robot])
            except StageError as exc:
                raise StageError(f"mapper: {name} is gone before its keyframe {kf_id} came ({exc})") from None
            if r is not None:
                self._push(robot, r)
        return rgbdmsgs.keyframe_from_msg(self.kept[robot][kf_id])[2]


class Follower:
    """The journal's ops applied to this mapper's map, with what the map's outputs need."""

    def __init__(self, mapper: Mapper, cfg: MapperConfig, frame: MapFrame, frames: RobotFrames | LeaderStream) -> None:
        self.mapper, self.cfg, self.map_frame, self.frames = mapper, cfg, frame, frames
        self.trajectories: list[list[tuple[int, int]]] = [[] for _ in cfg.robots]
        self.keyframes = self.refused = 0
        self.ms: list[float] = []
        self.problems: list[str] = []
        self.end: dict[str, Any] = {}

    def run(self, ops: Iterator[dict[str, Any]], bus: Bus, viz: Viz, publisher: MapSnapshots, out_dir: Path) -> None:
        pub_update = bus.publisher(MAP_UPDATE)
        for op in ops:
            while (q := bus.receive_nowait()) is not None:  # "save the map now", between keyframes
                answer_save(q, self.mapper, out_dir)
            kind = op.get("op")
            if kind == "end":
                self.end = op
                break
            if kind == "up":
                if op["up"]:
                    found = op.get("found") or {}
                    self.map_frame.use(op["up"], found.get("note", "the placing mapper's map frame"))
                continue
            if kind == "clear":  # the map built again in the defined order: so are the trajectories
                self.trajectories = [[] for _ in self.cfg.robots]
                self.keyframes = 0
            self._apply(op, pub_update, viz, publisher)
        if not self.end:
            raise InputError(f"mapper.follow {self.cfg.follow}: the journal ended without its end op")

    def _apply(self, op: dict[str, Any], pub_update: Publisher, viz: Viz, publisher: MapSnapshots) -> None:
        t0 = time.perf_counter()
        try:
            gid = apply_op(self.mapper, op, self.frames.frame)
        except (InputError, MapError) as exc:  # this mapper refused what the authority took: said, not hidden
            self.refused += 1
            self.problems.append(f"{self.cfg.robots[int(op.get('robot', 0))]}: {exc} (the placing mapper took it)")
            if op["op"] == "integrate":
                publish_update(pub_update, publisher, int(op["stamp"]), int(op["gid"]), 0, 0.0)
            return
        if gid is None:
            return
        ms = (time.perf_counter() - t0) * 1e3
        self.ms.append(ms)
        self.keyframes += 1
        stamp = int(op["stamp"])
        self.trajectories[int(op["robot"])].append((stamp, gid))
        kf = self.mapper.keyframes[gid]
        publish_update(pub_update, publisher, stamp, gid, 0 if kf.points_cam is None else len(kf.points_cam), ms)
        publisher.maybe(self.keyframes, stamp)
        if viz.enabled and publisher.every and self.keyframes % publisher.every == 0:
            log_map(viz, self.mapper, stamp, publisher.grid)

    def result(self) -> MapperResult:
        """The placing mapper's report (merges, links, robots lost and unplaced), this map's counts."""
        end = self.end
        return MapperResult(keyframes=self.keyframes, skipped=int(end.get("skipped", 0)) + self.refused,
                            corrections=int(end.get("corrections", 0)), ms=self.ms,
                            problems=list(end.get("problems", [])) + self.problems,
                            unmerged=list(end.get("unmerged", [])), merges=list(end.get("merges", [])),
                            links=dict(end.get("links", {})), lost=list(end.get("lost", [])))
