"""The mapper process: keyframes in; dense cloud, occupancy octree and map files out."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapper.config import MapperConfig
from octolog.bus import Bus, BusConfig
from octolog.errors import InputError, MapError
from octolog.viz import Viz
from schemas import codec
from schemas.topics import KEYFRAME, KEYFRAME_END, MAP_END, MAP_UPDATE


@dataclass
class MapperResult:
    keyframes: int = 0
    skipped: int = 0
    stats: dict = field(default_factory=dict)
    cloud_points: int = 0
    ms: list[float] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)


class Mapper:
    """Keyframes → filtered dense cloud + occupancy octree (the pure core of this stage)."""

    def __init__(self, cfg: MapperConfig) -> None:
        from mapper.cloud import DenseCloud
        from mapper.octree import OccupancyOctree

        self.cfg = cfg
        self.cloud = DenseCloud(voxel_m=cfg.voxel_m)
        self.octree = OccupancyOctree(resolution=cfg.resolution_m)

    def integrate(self, kf_id: int, world_from_camera: np.ndarray, frame) -> int:
        from mapper.cloud import keyframe_cloud

        if not np.all(np.isfinite(world_from_camera)):
            raise InputError(f"keyframe {kf_id}: pose is not finite")
        if not np.any(frame.depth):
            raise InputError(f"keyframe {kf_id}: no valid depth")
        world, cols = keyframe_cloud(
            frame.depth, frame.rgb, frame.intrinsics, frame.depth_scale_m, world_from_camera,
            max_range_m=self.cfg.max_range_m, stride=self.cfg.pixel_stride, nb_neighbors=self.cfg.sor_neighbors,
            std_ratio=self.cfg.sor_std_ratio, voxel_m=self.cfg.voxel_m, sor_first=self.cfg.sor_first)
        if len(world) == 0:
            raise InputError(f"keyframe {kf_id}: no valid depth within {self.cfg.max_range_m} m")
        self.cloud.add(kf_id, world, cols)
        self.octree.insert(world, world_from_camera[:3, 3], max_range_m=self.cfg.max_range_m)
        return len(world)

    def write(self, out_dir: Path, stem: str = "map") -> dict[str, str]:
        from mapper.cloud import write_ply

        out_dir.mkdir(parents=True, exist_ok=True)
        bt, ply = out_dir / f"{stem}.bt", out_dir / "cloud.ply"
        self.octree.write_bt(bt)
        pts, cols = self.cloud.cloud()
        write_ply(ply, pts, cols)
        return {"bt": str(bt), "ply": str(ply)}


def run(cfg: MapperConfig, bus_cfg: BusConfig, *, out_dir: Path, rerun: str = "off",
        recording_id: str = "octolog") -> MapperResult:
    mapper = Mapper(cfg)
    with Bus(bus_cfg, "mapper") as bus, Viz(rerun, "mapper", recording_id) as viz:
        result = consume(mapper, cfg, bus, viz)
        result.files = mapper.write(out_dir)
        result.stats = mapper.octree.stats()
        result.cloud_points = len(mapper.cloud.cloud()[0])
        (out_dir / "map_stats.json").write_text(json.dumps(
            {**result.stats, "cloud_points": result.cloud_points, "keyframes": result.keyframes,
             "skipped_keyframes": result.skipped}, indent=2, sort_keys=True) + "\n")
        if viz.enabled:
            _log_map(viz, mapper)
        bus.publisher(MAP_END).put(codec.stream_end_msg(MAP_UPDATE.name, result.keyframes + result.skipped))
    return result


def consume(mapper: Mapper, cfg: MapperConfig, bus: Bus, viz: Viz) -> MapperResult:
    pub_update = bus.publisher(MAP_UPDATE)
    bus.subscribe([KEYFRAME, KEYFRAME_END])
    bus.watch(cfg.wait_for)
    bus.wait_for(cfg.wait_for, cfg.wait_timeout_s)
    bus.announce()
    bus.watch(["tracker"])
    result = MapperResult()
    expected: int | None = None
    received = 0
    while expected is None or received < expected:
        r = bus.receive()
        if r is None:
            continue
        if r.topic == KEYFRAME_END:
            expected = int(r.decode().count)
            bus.expect_count(KEYFRAME, received, expected)
            bus.unwatch("tracker")
            continue
        received += 1
        t0 = time.perf_counter()
        msg = r.decode()
        try:
            kf_id, pose, frame = codec.keyframe_from_msg(msg)
            n = mapper.integrate(kf_id, pose, frame)
            result.keyframes += 1
        except (InputError, MapError):
            # a bad keyframe is counted and skipped; the map is never touched by it
            result.skipped += 1
            kf_id, n, frame = int(msg.id), 0, None
        ms = (time.perf_counter() - t0) * 1e3
        result.ms.append(ms)
        stats = mapper.octree.stats()
        stamp = codec.stamp_ns(msg.header)
        pub_update.put(codec.msgtype(MAP_UPDATE.msgtype)(
            header=codec.header(stamp, "world"), keyframe_id=kf_id, n_points=n,
            n_occupied=int(stats["occupied_voxels"]), n_free=int(stats["free_voxels"]), processing_ms=ms))
        if viz.enabled and frame is not None:
            viz.set_time(stamp, frame.seq)
            viz.scalar("mapper/ms", ms)
            viz.scalar("mapper/occupied", float(stats["occupied_voxels"]))
    return result


def _log_map(viz: Viz, mapper: Mapper) -> None:
    pts, cols = mapper.cloud.cloud()
    viz.points3d("world/mapper/cloud", pts, cols, radius=0.004, static=True)
    centres = mapper.octree.occupied_centres()
    if len(centres):
        z = centres[:, 2]
        t = (z - z.min()) / max(1e-9, float(np.ptp(z)))
        colours = np.stack([255 * t, 80 + 100 * (1 - t), 255 * (1 - t)], axis=1).astype(np.uint8)
        viz.boxes("world/mapper/occupied", centres, mapper.cfg.resolution_m, colours, static=True)
