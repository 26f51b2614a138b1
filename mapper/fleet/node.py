"""The mapper process for several robots: one session per robot namespace, their items merged in the
defined order (mapper/fleet/order.py) into one map; the per-robot trajectories and merge events out."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from octolog.kit.bus import Bus, BusConfig, Publisher, Received
from octolog.kit.config import to_dict
from octolog.kit.errors import InputError, MapError, StageError
from octolog.kit.geometry import RgbdFrame, matrix_to_pose
from octolog.kit.metrics import write_tum
from octolog.kit.viz import Viz
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import Mapper, make_mapper
from octolog.mapper.fleet.assembly import FleetHooks, FleetMap
from octolog.mapper.fleet.journal import Journal
from octolog.mapper.fleet.order import CorrectionItem, FleetMerge, KeyframeItem, Watermark
from octolog.mapper.fleet.placement import Merge, Placement
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
from octolog.schemas import codec, streammsgs
from octolog.schemas.msgtypes import CompressedKeyframeMsg, KeyframeMsg
from octolog.schemas.topics import (
    CONFIGS,
    KEYFRAME,
    KEYFRAME_COMPRESSED,
    KEYFRAME_END,
    KEYFRAME_POSES,
    MAP_MERGE,
    MAP_PLACED,
    MAP_SAVE,
    MAP_UPDATE,
    TRACKING_STATUS,
    Topic,
    route_topic,
)

log = logging.getLogger(__name__)

# Each robot's inbox is unbounded. The merge waits on one robot while others run ahead; a full
# inbox would block a thread of Zenoh's receive pool (shared by every session of the process, two
# threads on two cores), and with as many robots ahead as threads the awaited robot's samples
# could never arrive. Nothing is saved by bounding it: the merge keeps every item (FleetMerge.history).
ROBOT_INBOX = 0

# (robot, keyframe id) -> the topic and message it came as, for routing it to the shards it reaches
Payloads = dict[tuple[int, int], tuple[Topic, KeyframeMsg | CompressedKeyframeMsg]]

ROBOT_COLOURS = ((255, 160, 0), (0, 200, 255), (120, 220, 60), (230, 60, 160), (160, 120, 255), (250, 230, 40))


def run_fleet(cfg: MapperConfig, bus_cfg: BusConfig, *, out_dir: Path, rerun: str = "off",
              recording_id: str = "octolog") -> MapperResult:
    """One mapper for several robots: one Zenoh session per robot namespace (each subscribes to that
    robot's keyframes and announces the mapper there), one for the map outputs in the mapper's own
    namespace. Keyframes are merged in the order mapper/fleet/order.py defines. A shard that places
    (no `mapper.follow`) is its map's placement authority: one more session announces the stage
    `placement` and publishes the journal of its calls on the map (mapper/fleet/journal.py)."""
    mapper = make_mapper(cfg)
    with contextlib.ExitStack() as stack:
        bus = stack.enter_context(Bus(bus_cfg, cfg.stage, inbox_size=INBOX_KEYFRAMES))
        robot_buses = [stack.enter_context(Bus(dataclasses.replace(bus_cfg, namespace=r), cfg.stage,
                                               inbox_size=ROBOT_INBOX)) for r in cfg.robots]
        viz = stack.enter_context(Viz(rerun, "mapper", recording_id))
        frame = MapFrame(mapper, bus, viz, from_imu=False, ask=None if cfg.grid_up else robot_buses[0])
        payloads: Payloads = {}
        journal = _journal(stack, cfg, bus_cfg, mapper, frame, payloads)
        publisher = MapSnapshots(bus, mapper, cfg.publish_every)
        result, trajectories = consume_fleet(mapper, cfg, bus, robot_buses, viz, publisher, out_dir, frame, journal,
                                             payloads if journal is not None else None)
        per_robot = write_trajectories(mapper, cfg.robots, trajectories, out_dir)
        for robot in per_robot:  # placed by its start pose or by a shared place, or left out
            per_robot[robot]["merged"] = robot not in result.unmerged
            per_robot[robot]["lost"] = robot in result.lost
        frame.from_first_robot(None)  # no keyframe came: announce the level frame
        stats = {"robots": per_robot, "merges": result.merges, "links": result.links, **({"map_frame": frame.found} if frame.found else {})}
        if journal is not None:
            journal.end(summary(result))
            journal.write(out_dir)
        finish(mapper, result, bus, viz, publisher, out_dir, stats)
    return result


def _journal(stack: contextlib.ExitStack, cfg: MapperConfig, bus_cfg: BusConfig, mapper: Mapper,
             frame: MapFrame, payloads: Payloads) -> Journal | None:
    """A placing shard's journal, published by the stage `placement` in the mapper's namespace, which
    also routes each keyframe, as its robot sent it, to the shards it reaches (`route_topic`)."""
    if not cfg.shard:
        return None
    placing = stack.enter_context(Bus(bus_cfg, "placement"))
    placing.start([])
    pub = placing.publisher(MAP_PLACED)
    msg = codec.msgtype(MAP_PLACED.msgtype)
    routes: dict[Topic, Publisher] = {}

    def route(shard: int, robot: int, kf_id: int) -> None:
        topic, keyframe = payloads[(robot, kf_id)]
        key = route_topic(shard, robot, topic == KEYFRAME_COMPRESSED)
        if key not in routes:
            routes[key] = placing.publisher(key)
        routes[key].put(keyframe)

    return Journal(mapper, cfg.robots, lambda line: pub.put(msg(data=line)), lambda: frame.found, route)


def summary(result: MapperResult) -> dict:
    """What the placing mapper reports at the end of its journal (and a follower repeats)."""
    return {"keyframes": result.keyframes, "skipped": result.skipped, "corrections": result.corrections,
            "merges": result.merges, "links": result.links, "unmerged": result.unmerged, "lost": result.lost,
            "problems": result.problems}


def consume_fleet(mapper: Mapper, cfg: MapperConfig, bus: Bus, robot_buses: list[Bus], viz: Viz,
                  publisher: MapSnapshots, out_dir: Path, frame_of_map: MapFrame | None = None,
                  journal: Journal | None = None,
                  payloads: Payloads | None = None) -> tuple[MapperResult, list[list[tuple[int, int]]]]:
    """Receive every robot's keyframes and corrections and integrate them in the merge's order;
    without start poses, place the robots from the places they share (mapper/fleet/placement.py). A robot
    silent for `mapper.robot_stall_s` is paused: the others go on, and if anything was taken out of
    the defined order meanwhile, the map is built again in that order at the end (mapper/fleet/order.py)."""
    n = len(cfg.robots)
    pub_update, pub_merge = bus.publisher(MAP_UPDATE), bus.publisher(MAP_MERGE)
    _start_buses(cfg, bus, robot_buses)
    streams = _RobotStreams(cfg, robot_buses, FleetMerge(cfg.robots), MapperResult(), n)
    streams.payloads = payloads
    merge = streams.merge
    fm = _live_map(mapper, cfg, viz, publisher, pub_update, pub_merge, frame_of_map, journal)
    while not merge.done():
        while (q := bus.receive_nowait()) is not None:  # "save the map now", between keyframes
            answer_save(q, mapper, out_dir)
        nxt = merge.pop()
        if nxt is None:
            streams.take_next(viz)
            continue
        i, item = nxt
        streams.heard = [time.monotonic()] * n  # the merge moved: every robot's silence counts from now
        fm.apply(i, item)
        for k in range(n):  # a stream whose last item was just taken has ended
            if k not in streams.lost and streams.expected[k] is not None and streams.received[k] >= streams.expected[k] \
                    and not merge.has_items(k):
                merge.end(k)
    return _settle(mapper, cfg, streams, fm, out_dir, journal)


def _start_buses(cfg: MapperConfig, bus: Bus, robot_buses: list[Bus]) -> None:
    """The mapper's own session takes saves and announces its config; each robot's session subscribes."""
    bus.accept(MAP_SAVE)
    bus.start([])
    bus.publisher(CONFIGS["mapper"]).put(streammsgs.config_msg("mapper", to_dict(cfg)))
    for rb in robot_buses:
        # the tracker's statuses are the robot's watermark (mapper/fleet/order.py); in order with its
        # keyframes, and those in a row collapse in the inbox, so they never hold the tracker back
        rb.start([KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_POSES, KEYFRAME_END, TRACKING_STATUS], wait_for=cfg.wait_for,
                 timeout_s=cfg.wait_timeout_s, latest_only=[TRACKING_STATUS])
        rb.watch(["tracker"])


def _live_map(mapper: Mapper, cfg: MapperConfig, viz: Viz, publisher: MapSnapshots, pub_update: Publisher,
              pub_merge: Publisher, frame_of_map: MapFrame | None, journal: Journal | None) -> FleetMap:
    """The fleet map whose hooks publish as it grows: merge events, map updates, snapshots, Rerun."""

    def integrated(r: int, stamp: int, gid: int, pts: int, ms: float, frame: RgbdFrame) -> None:
        publish_update(pub_update, publisher, stamp, gid, pts, ms)
        publisher.maybe(fm.keyframes, stamp)
        if viz.enabled:
            viz.set_time(stamp, frame.seq)
            _log_robot(viz, mapper, cfg.robots[r], r, fm.trajectories[r])
            if publisher.every and fm.keyframes % publisher.every == 0:
                log_map(viz, mapper, stamp, publisher.grid)

    hooks = FleetHooks(
        merged=lambda m: _announce(m, cfg, pub_merge, viz),
        first=lambda W: frame_of_map.from_first_robot(W) if frame_of_map is not None else None,
        integrated=integrated,
        refused=lambda stamp, kid, ms: publish_update(pub_update, publisher, stamp, kid, 0, ms))
    fm = FleetMap(mapper, cfg.robots, _placement(cfg), hooks, journal)
    return fm


class _RobotStreams:
    """Every robot's stream as it arrives: what its tracker announced, what came, when it was last heard."""

    def __init__(self, cfg: MapperConfig, robot_buses: list[Bus], merge: FleetMerge, result: MapperResult,
                 n: int) -> None:
        self.cfg, self.robot_buses, self.merge, self.result, self.n = cfg, robot_buses, merge, result, n
        self.expected: list[int | None] = [None] * n
        self.received = [0] * n
        self.expected_poses, self.received_poses = [0] * n, [0] * n
        self.lost: set[int] = set()
        self.heard = [time.monotonic()] * n  # when each robot last sent something (or the wait began)
        self.turn = 0
        self.payloads: Payloads | None = None  # for routing the keyframes (a placing shard)

    def lose(self, k: int, exc: StageError) -> None:
        """Robot k is gone (its tracker died, or its data was lost for good): its stream ends with
        what arrived, and the other robots go on."""
        self.lost.add(k)
        self.robot_buses[k].unwatch("tracker")
        self.merge.end(k)
        self.result.problems.append(f"{self.cfg.robots[k]}: lost mid-run after {self.received[k]} keyframes ({exc}); "
                                    f"what arrived is in the map")

    def take_next(self, viz: Viz) -> None:
        """The order is not decided yet: take whatever any robot has sent, else wait for the next
        message of a robot whose stream is empty (the paused ones in turn when nobody else is awaited)."""
        if self._take_waiting():
            return
        merge, expected, received = self.merge, self.expected, self.received
        candidates = merge.waiting_on() or merge.paused()
        i = candidates[self.turn % len(candidates)]
        self.turn += 1
        try:
            r = self.robot_buses[i].receive()
            if r is None and expected[i] is not None:
                self.robot_buses[i].expect_count(KEYFRAME, received[i], expected[i])
        except StageError as exc:
            self.lose(i, exc)
            return
        if r is None:
            self._silent(i, viz)
        else:
            self._take(i, r)

    def _take_waiting(self) -> bool:
        """Every robot's waiting messages into the merge (so a silent robot's pause sees what the
        others sent); whether there were any."""
        took = False
        for k, rb in enumerate(self.robot_buses):
            while k not in self.lost and (r := rb.receive_nowait()) is not None:
                self._take(k, r)
                took = True
        return took

    def _take(self, i: int, r: Received) -> None:
        """Robot i's message into its stream; the stream ends with its last announced item."""
        self.heard[i] = time.monotonic()
        self._push(i, r)
        if self.expected[i] is not None and self.received[i] >= self.expected[i] \
                and self.received_poses[i] >= self.expected_poses[i] and not self.merge.has_items(i):
            self.merge.end(i)

    def _silent(self, i: int, viz: Viz) -> None:
        """Nothing from robot i: check every robot's link, and pause robot i if it stalls the others."""
        cfg, merge = self.cfg, self.merge
        for k, rb in enumerate(self.robot_buses):
            if k not in self.lost:
                try:
                    rb.check_peers()
                except StageError as exc:
                    self.lose(k, exc)
        silent = time.monotonic() - self.heard[i]
        if cfg.robot_stall_s and silent > cfg.robot_stall_s and i in merge.waiting_on() \
                and any(merge.has_items(k) for k in range(self.n)):
            merge.pause(i)  # alive but silent: the others go on (its later items come late)
            note = (f"{cfg.robots[i]}: silent for {silent:.0f} s (mapper.robot_stall_s {cfg.robot_stall_s:g}): "
                    f"the others went on without it")
            self.result.problems.append(note)
            # now, not at the end: an operator is waiting (the stage's log, as the tracker's warnings; Rerun)
            log.warning("%s", note)
            viz.text("mapper/events", note)

    def _push(self, i: int, r: Received) -> None:
        """Robot i's message into its stream: a stream end, a watermark, a correction or a keyframe."""
        merge = self.merge
        if r.topic == KEYFRAME_END:
            end = r.decode()
            if end.topic == KEYFRAME_POSES.name:  # corrections end before keyframes, on one publisher
                self.expected_poses[i] = int(end.count)
            elif end.topic in (KEYFRAME.name, KEYFRAME_COMPRESSED.name):
                self.expected[i] = int(end.count)
                self.robot_buses[i].expect_count(KEYFRAME, self.received[i], self.expected[i])
                self.robot_buses[i].unwatch("tracker")
        elif r.topic == TRACKING_STATUS:
            merge.push(i, Watermark(codec.stamp_ns(r.decode().header)))
        elif r.topic == KEYFRAME_POSES:
            self.received_poses[i] += 1
            msg = r.decode()
            merge.push(i, CorrectionItem(codec.stamp_ns(msg.header), msg))
        else:
            self.received[i] += 1
            msg = r.decode()
            merge.push(i, KeyframeItem(codec.stamp_ns(msg.header), int(msg.id), msg))
            if self.payloads is not None:
                self.payloads[(i, int(msg.id))] = (r.topic, msg)


def _settle(mapper: Mapper, cfg: MapperConfig, streams: _RobotStreams, live: FleetMap,
            out_dir: Path, journal: Journal | None = None) -> tuple[MapperResult, list[list[tuple[int, int]]]]:
    """The result once every stream has ended: the map built again in the defined order if a pause let
    items through out of it, the robots lost, placed and never placed (each of those a map of its own)."""
    result, fm = streams.result, live
    if streams.merge.jumped:
        # a pause let items through out of the defined order: the map, the placements and the joint
        # graph are built again from every item in that order, so the result does not depend on timing
        mapper.clear()
        if journal is not None:
            journal.cleared()
        fm = FleetMap(mapper, cfg.robots, _placement(cfg), journal=journal)
        for i, item in streams.merge.canonical():
            fm.apply(i, item)
        result.problems.append("the map was built again in the defined order (a silent robot's items came late)")
    result.keyframes, result.skipped, result.corrections = fm.keyframes, fm.skipped, fm.corrections
    result.ms = live.ms
    result.problems = live.problems + result.problems + (fm.problems if fm is not live else [])
    placement = fm.placement
    result.lost = [cfg.robots[r] for r in sorted(streams.lost)]
    result.unmerged = [cfg.robots[r] for r in placement.unplaced()]
    result.merges = [merge_event(m, cfg.robots) for m in placement.merges]
    result.links = {kind: placement.link_kinds.count(kind) for kind in ("place", "refine", "relink")}
    for r in placement.unplaced():
        waiting = placement.take(r)
        where = write_separate_map(cfg, waiting, out_dir / cfg.robots[r].strip("/").replace("/", "_"))
        result.problems.append(f"{cfg.robots[r]}: never placed (no verified place shared with the map): its "
                               f"{len(waiting)} keyframes are in a map of their own, {where}")
    return result, fm.trajectories


def _placement(cfg: MapperConfig) -> Placement:
    """Known start poses, or (none given, several robots) placing by shared places."""
    n = len(cfg.robots)
    return Placement.known(cfg.start_pose_matrices()) if cfg.start_poses or n == 1 else Placement.by_place(n, cfg.relink_after_m)


def write_separate_map(cfg: MapperConfig, waiting: list, out: Path) -> Path:
    """An unplaced robot's keyframes, in its own world, as a map of their own (its folder)."""
    own = make_mapper(cfg)
    for gid, w in enumerate(waiting):
        try:
            own.integrate(gid, w.robot_from_camera, w.frame)
        except (InputError, MapError):
            continue
    own.write(out)
    return out


def merge_event(m: Merge, robots: tuple[str, ...]) -> dict:
    """A merge as the bus, the session log and map_stats.json give it."""
    t, q = matrix_to_pose(m.world_from_robot)
    return {"robot": robots[m.robot], "robot_keyframe": m.robot_kf, "map_keyframe": m.map_gid,
            "inliers": m.alignment.inliers, "matches": m.alignment.matches,
            "world_from_robot": [float(x) for x in (*t, *q)]}


def _announce(m: Merge, cfg: MapperConfig, pub: Publisher, viz: Viz) -> None:
    """A robot just placed: the merge event on the bus (so in the session log) and in Rerun."""
    event = merge_event(m, cfg.robots)
    pub.put(codec.msgtype(MAP_MERGE.msgtype)(data=json.dumps(event, sort_keys=True)))
    viz.text("mapper/events", f"merged {cfg.robots[m.robot]} into the map: its keyframe {m.robot_kf} sees map "
                              f"keyframe {m.map_gid} ({m.alignment.inliers} of {m.alignment.matches} matches agree)")


def write_trajectories(mapper: Mapper, robots: tuple[str, ...], trajectories: list[list[tuple[int, int]]],
                       out_dir: Path) -> dict[str, dict]:
    """Each robot's keyframe trajectory in the common world (corrected poses), TUM format."""
    out_dir.mkdir(parents=True, exist_ok=True)
    per_robot = {}
    for robot, traj in zip(robots, trajectories):
        path = out_dir / f"keyframes_{robot.strip('/').replace('/', '_')}.txt"
        stamps = np.array([s for s, _ in traj], dtype=np.int64)
        poses = np.array([mapper.keyframes[g].world_from_camera for _, g in traj]).reshape(-1, 4, 4)
        write_tum(path, stamps, poses)
        per_robot[robot] = {"keyframes": len(traj), "trajectory": path.name}
    return per_robot


def _log_robot(viz: Viz, mapper: Mapper, robot: str, index: int, traj: list[tuple[int, int]]) -> None:
    ent = f"world/{robot.strip('/')}"
    colour = ROBOT_COLOURS[index % len(ROBOT_COLOURS)]
    xyz = np.array([mapper.keyframes[g].world_from_camera[:3, 3] for _, g in traj])
    viz.pose(f"{ent}/camera", mapper.keyframes[traj[-1][1]].world_from_camera)
    viz.path3d(f"{ent}/trajectory", xyz, color=list(colour))
    viz.points3d(f"{ent}/keyframes", xyz, list(colour), radius=0.03)
