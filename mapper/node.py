"""The mapper process: keyframes and pose corrections in; map snapshots on the bus; map files out."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapper.config import MapperConfig, make_mapper
from mapper.core import Mapper, bt_payload
from octolog.bus import Bus, BusConfig
from octolog.errors import InputError, MapError
from octolog.viz import Viz
from schemas import codec
from schemas.topics import (
    GRID, KEYFRAME, KEYFRAME_END, KEYFRAME_POSES, MAP_END, MAP_QUERY, MAP_SAVE, MAP_UPDATE, OCCUPIED, OCTOMAP,
)


@dataclass
class MapperResult:
    keyframes: int = 0
    skipped: int = 0
    corrections: int = 0
    stats: dict = field(default_factory=dict)
    cloud_points: int = 0
    ms: list[float] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)


class Publisher:
    """Map snapshots: published every n keyframes and at the end, and served to late joiners."""

    def __init__(self, bus: Bus, mapper: Mapper, every: int) -> None:
        self.bus, self.mapper, self.every = bus, mapper, every
        self.pub_octomap, self.pub_occupied = bus.publisher(OCTOMAP), bus.publisher(OCCUPIED)
        self.pub_grid = bus.publisher(GRID)
        self.grid = None
        self.latest: bytes | None = None  # immutable bytes: swapped atomically, read by the queryable
        self.stats: dict = {}
        bus.serve(MAP_QUERY, lambda: self.latest)

    def maybe(self, n_integrated: int, stamp: int) -> None:
        if self.every and n_integrated % self.every == 0:
            self.now(stamp)

    def now(self, stamp: int) -> None:
        octree = self.mapper.octree
        msg = codec.octomap_msg(bt_payload(octree.bt_bytes()), self.mapper.resolution_m, stamp)
        self.latest = self.pub_octomap.put(msg)
        self.pub_occupied.put(codec.point_cloud_msg(octree.occupied_centres(), stamp))
        self.grid = self.mapper.grid.project(octree)
        if self.grid is not None:
            from mapper.grid import occupancy_grid_msg

            self.pub_grid.put(occupancy_grid_msg(self.grid, stamp))
        self.stats = octree.stats()


def run(cfg: MapperConfig, bus_cfg: BusConfig, *, out_dir: Path, rerun: str = "off",
        recording_id: str = "octolog") -> MapperResult:
    mapper = make_mapper(cfg)
    with Bus(bus_cfg, "mapper") as bus, Viz(rerun, "mapper", recording_id) as viz:
        publisher = Publisher(bus, mapper, cfg.publish_every)
        result = consume(mapper, cfg, bus, viz, publisher, out_dir)
        last_stamp = max((kf.stamp_ns for kf in mapper.keyframes.values()), default=0)
        publisher.now(last_stamp)
        result.files = mapper.write(out_dir)
        result.stats = mapper.stats()
        result.cloud_points = len(mapper.cloud.cloud()[0])
        (out_dir / "map_stats.json").write_text(json.dumps(
            {**result.stats, "cloud_points": result.cloud_points, "skipped_keyframes": result.skipped,
             "corrections": result.corrections}, indent=2, sort_keys=True) + "\n")
        if viz.enabled:
            _log_map(viz, mapper, last_stamp, publisher.grid)
        bus.publisher(MAP_END).put(codec.stream_end_msg(MAP_UPDATE.name, result.keyframes + result.skipped))
    return result


def consume(mapper: Mapper, cfg: MapperConfig, bus: Bus, viz: Viz, publisher: Publisher,
            out_dir: Path) -> MapperResult:
    pub_update = bus.publisher(MAP_UPDATE)
    bus.accept(MAP_SAVE)
    bus.start([KEYFRAME, KEYFRAME_POSES, KEYFRAME_END], wait_for=cfg.wait_for, timeout_s=cfg.wait_timeout_s)
    bus.watch(["tracker"])
    result = MapperResult()
    expected: int | None = None
    received = 0
    while expected is None or received < expected:
        r = bus.receive()
        if r is None:
            if expected is not None:
                bus.expect_count(KEYFRAME, received, expected)
            continue
        if r.topic == KEYFRAME_END:
            expected = int(r.decode().count)
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
            try:
                result.corrections += mapper.correct(codec.keyframe_poses_from_msg(r.decode()))
            except InputError as exc:  # the whole correction is refused; the map is unchanged
                result.problems.append(str(exc))
            continue
        received += 1
        t0 = time.perf_counter()
        msg = r.decode()
        stamp = codec.stamp_ns(msg.header)
        try:
            kf_id, pose, frame = codec.keyframe_from_msg(msg)
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


def _log_map(viz: Viz, mapper: Mapper, stamp: int, grid: Any = None) -> None:
    viz.set_time(stamp)
    pts, cols = mapper.cloud.cloud()
    viz.points3d("world/mapper/cloud", pts, cols, radius=0.004)
    centres = mapper.octree.occupied_centres()
    if len(centres):
        z = centres[:, 2]
        t = (z - z.min()) / max(1e-9, float(np.ptp(z)))
        colours = np.stack([255 * t, 80 + 100 * (1 - t), 255 * (1 - t)], axis=1).astype(np.uint8)
        viz.boxes("world/mapper/occupied", centres, mapper.resolution_m, colours)
    if grid is not None:
        # map_server colours, top row = largest y, as the PGM shows it
        image = np.full(grid.data.shape, 205, np.uint8)
        image[grid.data == 0], image[grid.data == 100] = 254, 0
        viz.image("mapper/grid", image[::-1])


def fetch_map(bus: Bus, timeout_s: float = 10.0) -> Any | None:
    """What a late joiner does: ask the mapper's queryable for the current map."""
    return bus.fetch(MAP_QUERY, timeout_s)
