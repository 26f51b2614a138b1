"""What both mapper processes share: their result, the map snapshots they publish, the end of a run."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from octolog.kit.bus import Bus, Publisher, Received
from octolog.kit.cpuclock import charge
from octolog.kit.errors import MapError
from octolog.kit.viz import Viz
from octolog.mapper.core import Mapper, bt_payload
from octolog.mapper.grid import OccupancyGrid2D, occupancy_grid_msg
from octolog.mapper.mapframe import MapFrame
from octolog.mapper.shards import write_shard
from octolog.schemas import codec, mapmsgs, streammsgs
from octolog.schemas.topics import GRID, MAP_END, MAP_QUERY, MAP_SAVE, MAP_UPDATE, OCCUPIED, OCTOMAP

log = logging.getLogger(__name__)

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


class MapSnapshots:
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


def finish(mapper: Mapper, result: MapperResult, bus: Bus, viz: Viz, publisher: MapSnapshots, out_dir: Path,
           extra_stats: dict | None = None) -> None:
    """The last snapshot, the map files and stats, the end message."""
    last_stamp = max((kf.stamp_ns for kf in mapper.keyframes.values()), default=0)
    if publisher.frame is not None:
        publisher.frame.resolve()  # the map frame settled before the files' cloud merge starts
    t0 = time.monotonic()
    rebuilds = mapper.rebuilds
    result.files = mapper.write(out_dir, meanwhile=lambda: publisher.now(last_stamp))
    log.info("the map of the final poses (%s) and its files: %.2f s", "rebuilt" if mapper.rebuilds > rebuilds
             else "as it stood", time.monotonic() - t0)
    result.stats = mapper.stats()
    result.cloud_points = len(mapper.map_cloud()[0])
    if mapper.params.tiles is not None:
        result.stats["shard"] = mapper.params.tiles.name
    (out_dir / "map_stats.json").write_text(json.dumps(
        {**result.stats, "cloud_points": result.cloud_points, "skipped_keyframes": result.skipped,
         "corrections": result.corrections, **(extra_stats or {})}, indent=2, sort_keys=True) + "\n")
    if mapper.params.tiles is not None:  # last: a shard killed before this has no shard file
        result.files["shard"] = str(write_shard(mapper, out_dir))
    if viz.enabled:
        log_map(viz, mapper, last_stamp, publisher.grid, final=True)
    bus.publisher(MAP_END).put(streammsgs.stream_end_msg(MAP_UPDATE.name, result.keyframes + result.skipped))


def publish_update(pub: Publisher, publisher: MapSnapshots, stamp: int, kf_id: int, pts: int, ms: float) -> None:
    pub.put(codec.msgtype(MAP_UPDATE.msgtype)(
        header=codec.header(stamp, "world"), keyframe_id=kf_id, n_points=pts,
        n_occupied=publisher.stats.get("occupied_voxels", 0), n_free=publisher.stats.get("free_voxels", 0),
        processing_ms=ms))


def answer_save(r: Received, mapper: Mapper, out_dir: Path) -> None:
    try:
        files = mapper.write(out_dir)
    except MapError as exc:
        files = {"error": str(exc)}
    r.reply(codec.msgtype(MAP_SAVE.msgtype)(data=json.dumps(files, sort_keys=True)), MAP_SAVE)


# The dense cloud of a snapshot while the map grows: every CLOUD_STRIDE-th point of each keyframe's
# filtered cloud, not merged across keyframes (the voxels show the growing map; a full cloud per
# snapshot made the mapper's recording grow with the square of the session, and merging every point
# for it cost a second a snapshot at 3 M points), and at most PREVIEW_POINTS in all (the stride grows
# with the map, so a snapshot's size stops growing with the session's length and the recording
# grows linearly). The last snapshot logs the merged cloud whole.
CLOUD_STRIDE = 8
PREVIEW_POINTS = 100_000


def log_map(viz: Viz, mapper: Mapper, stamp: int, grid: OccupancyGrid2D | None = None, *, final: bool = False) -> None:
    with charge("rerun"):
        _log_map(viz, mapper, stamp, grid, final)


def _log_map(viz: Viz, mapper: Mapper, stamp: int, grid: OccupancyGrid2D | None, final: bool) -> None:
    viz.set_time(stamp)
    pts, cols = mapper.map_cloud() if final else mapper.cloud.preview(CLOUD_STRIDE, PREVIEW_POINTS)
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
