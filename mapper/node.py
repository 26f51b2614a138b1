"""The mapper process: keyframes and pose corrections in; map snapshots on the bus; map files out."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.bus import Bus, BusConfig
from octolog.kit.config import to_dict
from octolog.kit.errors import InputError, MapError, StageError
from octolog.kit.geometry import RgbdFrame, matrix_to_pose
from octolog.kit.metrics import write_tum
from octolog.kit.viz import Viz
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import Mapper, bt_payload, make_mapper
from octolog.mapper.fleet import CorrectionItem, FleetMerge, KeyframeItem, Watermark
from octolog.mapper.fleetmap import FleetHooks, FleetMap
from octolog.mapper.grid import OccupancyGrid2D, occupancy_grid_msg
from octolog.mapper.mapframe import MapFrame
from octolog.mapper.placement import Merge, Placement
from octolog.schemas import codec, mapmsgs, posemsgs, rgbdmsgs, streammsgs
from octolog.schemas.topics import (
    CONFIGS,
    GRID,
    KEYFRAME,
    KEYFRAME_COMPRESSED,
    KEYFRAME_END,
    KEYFRAME_POSES,
    MAP_END,
    MAP_MERGE,
    MAP_QUERY,
    MAP_SAVE,
    MAP_UPDATE,
    OCCUPIED,
    OCTOMAP,
    TRACKING_STATUS,
)

# Keyframes come in bursts (a new place: one every few frames) that the mapper, at ~0.1-0.5 s each,
# works off later. A full inbox blocks Zenoh's receive thread (back-pressure), and a receive thread
# blocked for longer than the link's lease (10 s) loses the link: the 10-minute synthetic session
# did, after its first loop's 165 keyframes. Room for a long burst (~1.5 MB each, raw) avoids it.
INBOX_KEYFRAMES = 256


@dataclass
class MapperResult:
    """What the mapper did: counts, per-keyframe times, the files it wrote, the problems it skipped."""

    keyframes: int = 0
    skipped: int = 0
    corrections: int = 0
    stats: dict = field(default_factory=dict)
    cloud_points: int = 0
    ms: list[float] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    unmerged: list[str] = field(default_factory=list)  # robots never placed in the map (no shared place)
    merges: list[dict] = field(default_factory=list)  # robots placed by a shared place (merge_event)
    links: dict[str, int] = field(default_factory=dict)  # verified matches between robots, by kind
    lost: list[str] = field(default_factory=list)  # robots gone mid-run (their tracker died)


class Publisher:
    """Map snapshots: published every n keyframes and at the end, and served to late joiners."""

    def __init__(self, bus: Bus, mapper: Mapper, every: int) -> None:
        self.bus, self.mapper, self.every = bus, mapper, every
        self.pub_octomap, self.pub_occupied = bus.publisher(OCTOMAP), bus.publisher(OCCUPIED)
        self.pub_grid = bus.publisher(GRID)
        self.grid: OccupancyGrid2D | None = None
        self.latest: bytes | None = None  # immutable bytes: swapped atomically, read by the queryable
        self.stats: dict = {}
        self.frame: MapFrame | None = None  # decides the grid's up before the first grid
        bus.serve(MAP_QUERY, lambda: self.latest)

    def maybe(self, n_integrated: int, stamp: int) -> None:
        """Publish a snapshot if `n_integrated` keyframes is a multiple of the period."""
        if self.every and n_integrated % self.every == 0:
            self.now(stamp)

    def now(self, stamp: int) -> None:
        """Publish a snapshot now: the octomap, the occupied voxels and the 2D grid."""
        if self.frame is not None:
            self.frame.resolve()  # may move the map into the gravity-aligned frame: before publishing it
        octree = self.mapper.octree
        msg = mapmsgs.octomap_msg(bt_payload(octree.bt_bytes()), self.mapper.resolution_m, stamp)
        self.latest = self.pub_octomap.put(msg)
        self.pub_occupied.put(mapmsgs.point_cloud_msg(octree.occupied_centres(), stamp))
        self.grid = self.mapper.project_grid()
        if self.grid is not None:
            self.pub_grid.put(occupancy_grid_msg(self.grid, stamp))
        self.stats = octree.stats()


def run(cfg: MapperConfig, bus_cfg: BusConfig, *, out_dir: Path, rerun: str = "off",
        recording_id: str = "octolog") -> MapperResult:
    """The mapper process: consume keyframes until the tracker's stream ends, then write the map."""
    if cfg.robots:
        return run_fleet(cfg, bus_cfg, out_dir=out_dir, rerun=rerun, recording_id=recording_id)
    mapper = make_mapper(cfg)
    with Bus(bus_cfg, "mapper", inbox_size=INBOX_KEYFRAMES) as bus, Viz(rerun, "mapper", recording_id) as viz:
        publisher = Publisher(bus, mapper, cfg.publish_every)
        publisher.frame = MapFrame(mapper, bus, viz, from_imu=not cfg.grid_up)
        result = consume(mapper, cfg, bus, viz, publisher, out_dir)
        publisher.frame.resolve()  # before the last snapshot, if none came before it
        found = publisher.frame.found
        finish(mapper, result, bus, viz, publisher, out_dir, {"map_frame": found} if found else None)
    return result


def finish(mapper: Mapper, result: MapperResult, bus: Bus, viz: Viz, publisher: Publisher, out_dir: Path,
           extra_stats: dict | None = None) -> None:
    """The last snapshot, the map files and stats, the end message."""
    last_stamp = max((kf.stamp_ns for kf in mapper.keyframes.values()), default=0)
    publisher.now(last_stamp)
    result.files = mapper.write(out_dir)
    result.stats = mapper.stats()
    result.cloud_points = len(mapper.cloud.cloud()[0])
    (out_dir / "map_stats.json").write_text(json.dumps(
        {**result.stats, "cloud_points": result.cloud_points, "skipped_keyframes": result.skipped,
         "corrections": result.corrections, **(extra_stats or {})}, indent=2, sort_keys=True) + "\n")
    if viz.enabled:
        _log_map(viz, mapper, last_stamp, publisher.grid, final=True)
    bus.publisher(MAP_END).put(streammsgs.stream_end_msg(MAP_UPDATE.name, result.keyframes + result.skipped))


# --- several robots, one map ---------------------------------------------------------------------

ROBOT_COLOURS = ((255, 160, 0), (0, 200, 255), (120, 220, 60), (230, 60, 160), (160, 120, 255), (250, 230, 40))


def run_fleet(cfg: MapperConfig, bus_cfg: BusConfig, *, out_dir: Path, rerun: str = "off",
              recording_id: str = "octolog") -> MapperResult:
    """One mapper for several robots: one Zenoh session per robot namespace (each subscribes to that
    robot's keyframes and announces the mapper there), one for the map outputs in the mapper's own
    namespace. Keyframes are merged in the order mapper/fleet.py defines."""
    mapper = make_mapper(cfg)
    with contextlib.ExitStack() as stack:
        bus = stack.enter_context(Bus(bus_cfg, "mapper", inbox_size=INBOX_KEYFRAMES))
        robot_buses = [stack.enter_context(Bus(dataclasses.replace(bus_cfg, namespace=r), "mapper"))
                       for r in cfg.robots]
        viz = stack.enter_context(Viz(rerun, "mapper", recording_id))
        frame = MapFrame(mapper, bus, viz, from_imu=False, ask=None if cfg.grid_up else robot_buses[0])
        publisher = Publisher(bus, mapper, cfg.publish_every)
        result, trajectories = consume_fleet(mapper, cfg, bus, robot_buses, viz, publisher, out_dir, frame)
        per_robot = write_trajectories(mapper, cfg.robots, trajectories, out_dir)
        for robot in per_robot:  # placed by its start pose or by a shared place, or left out
            per_robot[robot]["merged"] = robot not in result.unmerged
            per_robot[robot]["lost"] = robot in result.lost
        frame.from_first_robot(None)  # no keyframe came: announce the level frame
        stats = {"robots": per_robot, "merges": result.merges, "links": result.links, **({"map_frame": frame.found} if frame.found else {})}
        finish(mapper, result, bus, viz, publisher, out_dir, stats)
    return result


def consume_fleet(mapper: Mapper, cfg: MapperConfig, bus: Bus, robot_buses: list[Bus], viz: Viz,
                  publisher: Publisher, out_dir: Path,
                  frame_of_map: MapFrame | None = None) -> tuple[MapperResult, list[list[tuple[int, int]]]]:
    """Receive every robot's keyframes and corrections and integrate them in the merge's order;
    without start poses, place the robots from the places they share (mapper/placement.py). A robot
    silent for `mapper.robot_stall_s` is paused: the others go on, and if anything was taken out of
    the defined order meanwhile, the map is built again in that order at the end (mapper/fleet.py)."""
    n = len(cfg.robots)
    pub_update, pub_merge = bus.publisher(MAP_UPDATE), bus.publisher(MAP_MERGE)
    bus.accept(MAP_SAVE)
    bus.start([])
    bus.publisher(CONFIGS["mapper"]).put(streammsgs.config_msg("mapper", to_dict(cfg)))
    for rb in robot_buses:
        # the tracker's statuses are the robot's watermark (mapper/fleet.py); in order with its
        # keyframes, and those in a row collapse in the inbox, so they never hold the tracker back
        rb.start([KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_POSES, KEYFRAME_END, TRACKING_STATUS], wait_for=cfg.wait_for,
                 timeout_s=cfg.wait_timeout_s, latest_only=[TRACKING_STATUS])
        rb.watch(["tracker"])
    merge = FleetMerge(cfg.robots)
    expected: list[int | None] = [None] * n
    received = [0] * n
    expected_poses, received_poses = [0] * n, [0] * n
    result = MapperResult()
    lost: set[int] = set()
    heard = [time.monotonic()] * n  # when each robot last sent something (or the wait began)
    turn = 0

    def integrated(r: int, stamp: int, gid: int, pts: int, ms: float, frame: RgbdFrame) -> None:
        _update(pub_update, publisher, stamp, gid, pts, ms)
        publisher.maybe(fm.keyframes, stamp)
        if viz.enabled:
            viz.set_time(stamp, frame.seq)
            _log_robot(viz, mapper, cfg.robots[r], r, fm.trajectories[r])
            if publisher.every and fm.keyframes % publisher.every == 0:
                _log_map(viz, mapper, stamp, publisher.grid)

    hooks = FleetHooks(
        merged=lambda m: _announce(m, cfg, pub_merge, viz),
        first=lambda W: frame_of_map.from_first_robot(W) if frame_of_map is not None else None,
        integrated=integrated,
        refused=lambda stamp, kid, ms: _update(pub_update, publisher, stamp, kid, 0, ms))
    fm = FleetMap(mapper, cfg.robots, _placement(cfg), hooks)

    def lose(k: int, exc: StageError) -> None:
        """Robot k is gone (its tracker died, or its data was lost for good): its stream ends with
        what arrived, and the other robots go on."""
        lost.add(k)
        robot_buses[k].unwatch("tracker")
        merge.end(k)
        result.problems.append(f"{cfg.robots[k]}: lost mid-run after {received[k]} keyframes ({exc}); "
                               f"what arrived is in the map")

    while not merge.done():
        while (q := bus.receive_nowait()) is not None:  # "save the map now", between keyframes
            _answer_save(q, mapper, out_dir)
        nxt = merge.pop()
        if nxt is None:
            # the order is not decided yet: take the next message of a robot whose stream is empty
            # (the paused ones in turn when nobody else is awaited)
            candidates = merge.waiting_on() or merge.paused()
            i = candidates[turn % len(candidates)]
            turn += 1
            try:
                r = robot_buses[i].receive()
                if r is None and expected[i] is not None:
                    robot_buses[i].expect_count(KEYFRAME, received[i], expected[i])
            except StageError as exc:
                lose(i, exc)
                continue
            if r is None:
                for k, rb in enumerate(robot_buses):
                    if k not in lost:
                        try:
                            rb.check_peers()
                        except StageError as exc:
                            lose(k, exc)
                silent = time.monotonic() - heard[i]
                if cfg.robot_stall_s and silent > cfg.robot_stall_s and i in merge.waiting_on() \
                        and any(merge.has_items(k) for k in range(n)):
                    merge.pause(i)  # alive but silent: the others go on (its later items come late)
                    note = (f"{cfg.robots[i]}: silent for {silent:.0f} s (mapper.robot_stall_s {cfg.robot_stall_s:g}): "
                            f"the others went on without it")
                    result.problems.append(note)
                    # now, not at the end: an operator is waiting (stderr, as the tracker's warnings; Rerun)
                    print(f"mapper: warning: {note}", file=sys.stderr, flush=True)
                    viz.text("mapper/events", note)
                continue
            heard[i] = time.monotonic()
            if r.topic == KEYFRAME_END:
                end = r.decode()
                if end.topic == KEYFRAME_POSES.name:  # corrections end before keyframes, on one publisher
                    expected_poses[i] = int(end.count)
                elif end.topic in (KEYFRAME.name, KEYFRAME_COMPRESSED.name):
                    expected[i] = int(end.count)
                    robot_buses[i].expect_count(KEYFRAME, received[i], expected[i])
                    robot_buses[i].unwatch("tracker")
            elif r.topic == TRACKING_STATUS:
                merge.push(i, Watermark(codec.stamp_ns(r.decode().header)))
            elif r.topic == KEYFRAME_POSES:
                received_poses[i] += 1
                msg = r.decode()
                merge.push(i, CorrectionItem(codec.stamp_ns(msg.header), msg))
            else:
                received[i] += 1
                msg = r.decode()
                merge.push(i, KeyframeItem(codec.stamp_ns(msg.header), int(msg.id), msg))
            if expected[i] is not None and received[i] >= expected[i] and received_poses[i] >= expected_poses[i] \
                    and not merge.has_items(i):
                merge.end(i)
            continue
        i, item = nxt
        heard = [time.monotonic()] * n  # the merge moved: every robot's silence counts from now
        fm.apply(i, item)
        for k in range(n):  # a stream whose last item was just taken has ended
            if k not in lost and expected[k] is not None and received[k] >= expected[k] and not merge.has_items(k):
                merge.end(k)
    live = fm
    if merge.jumped:
        # a pause let items through out of the defined order: the map, the placements and the joint
        # graph are built again from every item in that order, so the result does not depend on timing
        mapper.clear()
        fm = FleetMap(mapper, cfg.robots, _placement(cfg))
        for i, item in merge.canonical():
            fm.apply(i, item)
        result.problems.append("the map was built again in the defined order (a silent robot's items came late)")
    result.keyframes, result.skipped, result.corrections = fm.keyframes, fm.skipped, fm.corrections
    result.ms = live.ms
    result.problems = live.problems + result.problems + (fm.problems if fm is not live else [])
    placement = fm.placement
    result.lost = [cfg.robots[r] for r in sorted(lost)]
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


def _update(pub: Any, publisher: Publisher, stamp: int, kf_id: int, pts: int, ms: float) -> None:
    pub.put(codec.msgtype(MAP_UPDATE.msgtype)(
        header=codec.header(stamp, "world"), keyframe_id=kf_id, n_points=pts,
        n_occupied=publisher.stats.get("occupied_voxels", 0), n_free=publisher.stats.get("free_voxels", 0),
        processing_ms=ms))


def merge_event(m: Merge, robots: tuple[str, ...]) -> dict:
    """A merge as the bus, the session log and map_stats.json give it."""
    t, q = matrix_to_pose(m.world_from_robot)
    return {"robot": robots[m.robot], "robot_keyframe": m.robot_kf, "map_keyframe": m.map_gid,
            "inliers": m.alignment.inliers, "matches": m.alignment.matches,
            "world_from_robot": [float(x) for x in (*t, *q)]}


def _announce(m: Merge, cfg: MapperConfig, pub: Any, viz: Viz) -> None:
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


def _answer_save(r: Any, mapper: Mapper, out_dir: Path) -> None:
    try:
        files = mapper.write(out_dir)
    except MapError as exc:
        files = {"error": str(exc)}
    r.reply(codec.msgtype(MAP_SAVE.msgtype)(data=json.dumps(files, sort_keys=True)), MAP_SAVE)


def consume(mapper: Mapper, cfg: MapperConfig, bus: Bus, viz: Viz, publisher: Publisher,
            out_dir: Path) -> MapperResult:
    """Integrate keyframes and corrections until every one the tracker announced has arrived."""
    pub_update = bus.publisher(MAP_UPDATE)
    bus.accept(MAP_SAVE)
    bus.start([KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_POSES, KEYFRAME_END], wait_for=cfg.wait_for,
              timeout_s=cfg.wait_timeout_s)
    bus.publisher(CONFIGS["mapper"]).put(streammsgs.config_msg("mapper", to_dict(cfg)))
    bus.watch(["tracker"])
    result = MapperResult()
    expected: int | None = None
    received = 0
    # the tracker ends its corrections (keyframe_poses) before its keyframes, on one publisher
    expected_poses, received_poses = 0, 0
    while expected is None or received < expected or received_poses < expected_poses:
        r = bus.receive()
        if r is None:
            if expected is not None:
                bus.expect_count(KEYFRAME, received, expected)
                bus.expect_count(KEYFRAME_POSES, received_poses, expected_poses)
            continue
        if r.topic == KEYFRAME_END:
            end = r.decode()
            if end.topic == KEYFRAME_POSES.name:
                expected_poses = int(end.count)
                continue
            if end.topic not in (KEYFRAME.name, KEYFRAME_COMPRESSED.name):
                continue  # the end of a stream the mapper does not take (tracker/trajectory)
            expected = int(end.count)
            bus.expect_count(KEYFRAME, received, expected)
            bus.unwatch("tracker")
            continue
        if r.topic == MAP_SAVE:
            try:
                files = mapper.write(out_dir)
            except MapError as exc:
                files = {"error": str(exc)}
            r.reply(codec.msgtype(MAP_SAVE.msgtype)(data=json.dumps(files, sort_keys=True)), MAP_SAVE)
            continue
        if r.topic == KEYFRAME_POSES:
            received_poses += 1
            try:
                result.corrections += mapper.correct(posemsgs.keyframe_poses_from_msg(r.decode()))
            except InputError as exc:  # the whole correction is refused; the map is unchanged
                result.problems.append(str(exc))
            continue
        received += 1
        t0 = time.perf_counter()
        msg = r.decode()
        stamp = codec.stamp_ns(msg.header)
        try:
            kf_id, pose, frame = rgbdmsgs.keyframe_from_msg(msg)
            if publisher.frame is not None:
                publisher.frame.first_keyframe(frame)
            n = mapper.integrate(kf_id, pose, frame)
            result.keyframes += 1
        except (InputError, MapError) as exc:
            # a bad keyframe is counted, reported and skipped; the map is never touched by it
            result.skipped += 1
            result.problems.append(str(exc))
            kf_id, n, frame = int(msg.id), 0, None
        ms = (time.perf_counter() - t0) * 1e3
        result.ms.append(ms)
        pub_update.put(codec.msgtype(MAP_UPDATE.msgtype)(
            header=codec.header(stamp, "world"), keyframe_id=kf_id, n_points=n,
            # voxel counts as of the last snapshot: counting every keyframe costs more than integrating it
            n_occupied=publisher.stats.get("occupied_voxels", 0), n_free=publisher.stats.get("free_voxels", 0),
            processing_ms=ms))
        if frame is not None:
            publisher.maybe(result.keyframes, stamp)
            if viz.enabled:
                viz.set_time(stamp, frame.seq)
                viz.scalar("mapper/ms", ms)
                if publisher.every and result.keyframes % publisher.every == 0:
                    _log_map(viz, mapper, stamp, publisher.grid)
    return result


# The dense cloud of a snapshot while the map grows: every CLOUD_STRIDE-th point of each keyframe's
# filtered cloud, not merged across keyframes (the voxels show the growing map; a full cloud per
# snapshot made the mapper's recording grow with the square of the session, and merging every point
# for it cost a second a snapshot at 3 M points), and at most PREVIEW_POINTS in all (the stride grows
# with the map, so a snapshot's size stops growing with the session's length and the recording
# grows linearly). The last snapshot logs the merged cloud whole.
CLOUD_STRIDE = 8
PREVIEW_POINTS = 100_000


def _log_map(viz: Viz, mapper: Mapper, stamp: int, grid: Any = None, *, final: bool = False) -> None:
    viz.set_time(stamp)
    pts, cols = mapper.cloud.cloud() if final else mapper.cloud.preview(CLOUD_STRIDE, PREVIEW_POINTS)
    viz.points3d("map/cloud", pts, cols, radius=0.004 if final else 0.008)
    centres = mapper.octree.occupied_centres()
    if len(centres):
        # height: the octree is in `map`, z up (gravity when the source has an accelerometer)
        up = centres[:, 2]
        t = (up - up.min()) / max(1e-9, float(np.ptp(up)))
        colours = np.stack([255 * t, 80 + 100 * (1 - t), 255 * (1 - t)], axis=1).astype(np.uint8)
        viz.boxes("map/occupied", centres, mapper.resolution_m, colours)
    if grid is not None:
        # map_server colours, top row = largest y, as the PGM shows it
        image = np.full(grid.data.shape, 205, np.uint8)
        image[grid.data == 0], image[grid.data == 100] = 254, 0
        viz.image("mapper/grid", image[::-1])


def fetch_map(bus: Bus, timeout_s: float = 10.0) -> Any | None:
    """What a late joiner does: ask the mapper's queryable for the current map."""
    return bus.fetch(MAP_QUERY, timeout_s)
