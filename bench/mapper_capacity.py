"""How many robots one mapper serves: its cost per keyframe on a session's own keyframes, and what that
makes in keyframes a second and robots at the session's keyframe rate.

    python bench/mapper_capacity.py SESSION [SESSION ...] [--repeat 3]

Each SESSION is a folder of `octolog run`. Its logged keyframes and corrections (the tracker's
output, as the mapper took them) go through a fresh mapper with the default config in this process,
in log order; each keyframe's `Mapper.integrate` is timed whole, with the snapshot due at every
`publish_every`-th keyframe (the 2D grid, and the rebuild a correction left), and its cloud
building (`keyframe_cloud`: back-projection, outlier filter, voxel grid) on its own, so the rest is
the occupancy insert (ray casting, log-odds, colour), the dense cloud and the snapshots. Capacity = 1000 / the mean whole cost (ms): keyframes
a second one core integrates; robots served = capacity / the session's keyframes per second of
camera time (its tracker's keyframe rate). Medians over `--repeat` passes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from octolog.mapper import voxelmap
from octolog.mapper.cloud import backproject, image_outlier_removal, keyframe_cloud, voxel_downsample
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.mapper.fleet.order import CorrectionItem
from octolog.schemas import posemsgs, rgbdmsgs
from octolog.shell.merge import session_items


STEPS = ("back-projection", "outlier measure (image grid)", "1 cm voxel grid", "occupancy insert with colour",
         "the rest: dense cloud, snapshots (grid, rebuilds)")


def one_pass(items: list, cfg: MapperConfig) -> tuple[list[float], list[float], list[float], list[tuple]]:
    """(whole ms, cloud-building ms) per keyframe, ms per correction, and per keyframe the ms of
    each of STEPS (the cloud's steps timed again on their own, the insert inside `integrate`)."""
    mapper = make_mapper(cfg)
    c = mapper.params.cloud
    whole, cloud, corrections, steps = [], [], [], []
    inserts: list[float] = []
    insert = voxelmap.VoxelOccupancyMap.insert

    def timed_insert(self, *args, **kw):  # noqa: ANN001, ANN002, ANN003
        t = time.perf_counter()
        out = insert(self, *args, **kw)
        inserts.append((time.perf_counter() - t) * 1e3)
        return out

    voxelmap.VoxelOccupancyMap.insert = timed_insert
    try:
        _pass(items, cfg, mapper, c, whole, cloud, corrections, steps, inserts)
    finally:
        voxelmap.VoxelOccupancyMap.insert = insert
    return whole, cloud, corrections, steps


def _pass(items, cfg, mapper, c, whole, cloud, corrections, steps, inserts) -> None:  # noqa: ANN001
    for item in items:
        if isinstance(item, CorrectionItem):
            t0 = time.perf_counter()
            mapper.correct(posemsgs.keyframe_poses_from_msg(item.poses), item.poses.depth_inverse_offset)
            corrections.append((time.perf_counter() - t0) * 1e3)  # the rebuild it asks for comes at the next snapshot
            continue
        kf_id, pose, frame = rgbdmsgs.keyframe_from_msg(item.payload)
        stride = mapper._stride(frame.stamp_ns)
        t0 = time.perf_counter()
        keyframe_cloud(frame.depth, frame.rgb, frame.intrinsics, frame.depth_scale_m, np.eye(4),
                       max_range_m=c.max_range_m, stride=stride, nb_neighbors=c.sor_neighbors,
                       std_ratio=c.sor_std_ratio, voxel_m=c.voxel_m, sor_first=c.sor_first, outliers=c.outliers,
                       inverse_offset=frame.depth_inverse_offset)
        t1 = time.perf_counter()
        inserts.clear()
        mapper.integrate(kf_id, pose, frame)
        insert_ms = sum(inserts)
        if cfg.publish_every and len(mapper.keyframes) % cfg.publish_every == 0:
            mapper.project_grid()  # a snapshot: the octree (rebuilt if a correction left it stale) and the grid
        t2 = time.perf_counter()
        cloud.append((t1 - t0) * 1e3)
        whole.append((t2 - t1) * 1e3)
        a = time.perf_counter()
        backproject(frame.depth, frame.rgb, frame.intrinsics, frame.depth_scale_m, max_range_m=c.max_range_m,
                    stride=stride)
        b = time.perf_counter()
        p, col = image_outlier_removal(frame.depth, frame.rgb, frame.intrinsics, frame.depth_scale_m,
                                       max_range_m=c.max_range_m, stride=stride, std_ratio=c.sor_std_ratio)
        d = time.perf_counter()
        voxel_downsample(p, col, c.voxel_m)
        e = time.perf_counter()
        steps.append(((b - a) * 1e3, (d - b - (b - a)) * 1e3, (e - d) * 1e3, insert_ms,
                      whole[-1] - cloud[-1] - insert_ms))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cfg = MapperConfig()
    print("| session | keyframes, per s of camera | whole ms / keyframe, median / mean / p90 | of it: cloud building, "
          "median | insert, dense cloud, snapshots, median | corrections: count, ms each | "
          "capacity, keyframes/s | robots served |")
    print("|---|---|---|---|---|---|---|---|")
    breakdown = {}
    for folder in map(Path, args.sessions):
        items = session_items(folder)
        summary = json.loads((folder / "summary.json").read_text())
        passes = [one_pass(items, cfg) for _ in range(args.repeat)]
        whole = [statistics.median(v) for v in zip(*(p[0] for p in passes))]
        cloud = [statistics.median(v) for v in zip(*(p[1] for p in passes))]
        corr = [statistics.median(v) for v in zip(*(p[2] for p in passes))]
        n_kf = len(passes[0][3])
        breakdown[folder.name] = [float(np.median([statistics.median(p[3][i][j] for p in passes) for i in range(n_kf)]))
                                  for j in range(len(STEPS))]
        rate = len(whole) / summary["duration_s"]
        capacity = 1000.0 / float(np.mean(whole))
        print(f"| {summary['source']} | {len(whole)}, {rate:.1f} | {np.median(whole):.1f} / {np.mean(whole):.1f} / "
              f"{np.percentile(whole, 90):.1f} | {np.median(cloud):.1f} | {np.median(whole) - np.median(cloud):.1f} | "
              f"{len(corr)}, {np.median(corr) if corr else 0:.0f} | {capacity:.1f} | {capacity / rate:.1f} |", flush=True)
    print("\nper keyframe, medians (ms): " + ", ".join(breakdown))
    print("| step | " + " | ".join(breakdown) + " |")
    print("|---|" + "---|" * len(breakdown))
    for j, step in enumerate(STEPS):
        print(f"| {step} | " + " | ".join(f"{v[j]:.1f}" for v in breakdown.values()) + " |")


if __name__ == "__main__":
    main()
