"""A shard's tiles on disk (`shard.npz`), and the shards stitched into the whole map.

A mapper run with `mapper.shard = "K/N"` writes, with its map files (which hold its tiles only),
`shard.npz`: its occupancy voxels (packed OctoMap keys, log-odds, colour), its dense cloud (points,
colours, 1 cm voxel indices) and a header with everything the shards must agree on (tile rule,
voxel sizes, sensor model, map frame, grid band). It is written last, after the map files, and
renamed into place: a shard killed mid-run leaves none, so its tiles are missing, never half there.

`stitch` joins shards: the voxels of disjoint tiles side by side, sorted as one map sorts them, so
the `.bt`, `.ot`, `cloud.ply`/`.pcd` and the grid are the bytes one mapper writes for the same
keyframes. A shard that is missing is named; the map of the others is still written.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.files import read_npz, write_npz
from octolog.mapper.core import Mapper, project_grid, write_map_files
from octolog.mapper.params import GridParams
from octolog.mapper.sensor_model import SensorModel
from octolog.mapper.voxelmap import VoxelOccupancyMap

__all__ = ["SHARD_FILE", "stitch", "write_shard"]

SHARD_FILE = "shard.npz"
FORMAT = "octolog-map-shard"
VERSION = 1
# what every shard of one map has in common
AGREE = ("count", "tile_m", "rule", "resolution_m", "voxel_m", "colour", "sensor", "grid", "map_from_world")


def write_shard(mapper: Mapper, out_dir: Path, extra: dict[str, object] | None = None) -> Path:
    """`out_dir/shard.npz` of a shard's mapper (after its map files)."""
    tiles = mapper.params.tiles
    if tiles is None:
        raise ValueError("not a shard: mapper.shard is not set")
    octree = mapper.octree
    keys, logodds, colours = octree.voxels()
    points, point_colours = mapper.map_cloud()
    point_voxels = mapper.cloud.voxel_keys()
    if (keep := mapper.cloud_mask()) is not None:
        point_voxels = point_voxels[keep]
    header = {"format": FORMAT, "version": VERSION, **tiles.describe(),
              "resolution_m": mapper.resolution_m, "voxel_m": tiles.voxel_m, "colour": octree.colour,
              "sensor": asdict(octree.model), "grid": asdict(mapper.params.grid),
              "map_from_world": mapper.map_from_world.tolist(), "keyframes": len(mapper.keyframes),
              **(extra or {})}
    path = out_dir / SHARD_FILE
    write_npz(path, header, {"keys": keys, "logodds": logodds, "colours": colours, "points": points,
                             "point_colours": point_colours, "point_voxels": point_voxels})
    return path


def _read(folder: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    path = folder / SHARD_FILE if folder.is_dir() else folder
    if not path.is_file():
        raise InputError(f"{folder}: no {SHARD_FILE} (not a map shard, or its mapper did not finish)")
    try:
        header, arrays = read_npz(path)
    except (zipfile.BadZipFile, EOFError, ValueError, KeyError, OSError) as exc:
        raise InputError(f"{path}: damaged map shard ({type(exc).__name__}: {exc})") from None
    if header.get("format") != FORMAT or header.get("version") != VERSION:
        raise InputError(f"{path}: not a version-{VERSION} octolog map shard")
    return header, arrays


def stitch(folders: list[Path], out: Path) -> dict[str, Any]:
    """Join the shards in `folders` into one map in `out` (map files and map_stats.json); returns
    the stats, whose `missing_shards` and `problems` say what is not in it. InputError when no
    shard is readable or the shards are not of one map."""
    shards, problems = [], []
    for folder in folders:
        try:
            shards.append((folder, *_read(folder)))
        except InputError as exc:
            problems.append(str(exc))
    if not shards:
        raise InputError("octolog stitch: no readable shard (" + "; ".join(problems) + ")")
    first = shards[0][1]
    for folder, header, _ in shards[1:]:
        wrong = [k for k in AGREE if header.get(k) != first.get(k)]
        if wrong:
            raise InputError(f"{folder}: not a shard of the same map as {shards[0][0]} (differs in {', '.join(wrong)})")
    by_index: dict[int, Path] = {}
    for folder, header, _ in shards:
        if header["index"] in by_index:
            raise InputError(f"{folder}: shard {header['shard']} is also {by_index[header['index']]}")
        by_index[header["index"]] = folder
    count = int(first["count"])
    missing = [f"{k}/{count}" for k in range(1, count + 1) if k not in by_index]
    for name in missing:
        problems.append(f"shard {name} missing: its tiles are not in the map (re-run that shard and stitch again)")

    arrays = [a for _, _, a in shards]
    keys = np.concatenate([a["keys"] for a in arrays])
    order = np.argsort(keys, kind="stable")
    octree = VoxelOccupancyMap(float(first["resolution_m"]), model=SensorModel(**first["sensor"]),
                               colour=bool(first["colour"]))
    try:
        octree.set_voxels(keys[order], np.concatenate([a["logodds"] for a in arrays])[order],
                          np.concatenate([a["colours"] for a in arrays])[order])
    except ValueError:
        raise InputError("octolog stitch: the shards hold the same voxels (tiles overlap)") from None
    voxels = np.concatenate([a["point_voxels"] for a in arrays])
    cloud_order = np.lexsort((voxels[:, 2], voxels[:, 1], voxels[:, 0]))
    points = np.concatenate([a["points"] for a in arrays])[cloud_order]
    colours = np.concatenate([a["point_colours"] for a in arrays])[cloud_order]
    grid_params = GridParams(**{**first["grid"], "up": tuple(first["grid"]["up"])})
    map_from_world = np.array(first["map_from_world"], dtype=float)
    grid = project_grid(octree, grid_params, map_from_world)
    files = write_map_files(out, octree, points, colours, grid)
    stats = {**octree.stats(), "cloud_points": int(len(points)), "map_from_world": first["map_from_world"],
             "shards": {h["shard"]: {"folder": str(f), "keyframes": h["keyframes"]} for f, h, _ in shards},
             "missing_shards": missing, "problems": problems, "files": files}
    (out / "map_stats.json").write_text(json.dumps(stats, indent=2, sort_keys=True) + "\n")
    return stats
