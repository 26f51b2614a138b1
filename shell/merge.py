"""`octolog merge A B ... --out MERGED`: sessions recorded apart, one map, offline; and `octolog
stitch S1 S2 ... --out MAP`: a map's shards (mapper/shards.py) joined into the whole map.

Each session folder's log holds its tracker's keyframes and corrections; they go through the
fleet's merge (mapper/fleet) as if each session were a robot of one fleet, with no start poses:
the first session's world is the map's, every other session is placed where one of its keyframes
verifiably sees a place already in the map (then refined over more matches and settled in one pose
graph), in the defined order of the items' stamps. A session never placed is left out, said so in
one line, and written as a map of its own beside the merged one. The map is in the first session's
`map` frame (its config.toml's `mapper.grid_up`). `map_stats.json` holds the merge evidence (which
keyframes matched, how many matches agreed, where each session was placed). No transport, no
clock: the same sessions give the same bytes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import tomllib
from pathlib import Path

from octolog.kit.errors import ConfigError, InputError
from octolog.kit.mcaplog import read_wire, summarize
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.mapper.fleet.assembly import FleetMap
from octolog.mapper.fleet.node import merge_event, write_separate_map, write_trajectories
from octolog.mapper.fleet.order import CorrectionItem, KeyframeItem, merged_order
from octolog.mapper.fleet.placement import Placement
from octolog.mapper.shards import stitch
from octolog.schemas import codec
from octolog.schemas.topics import KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_POSES


def session_items(folder: Path) -> list[KeyframeItem | CorrectionItem]:
    """A session's keyframes and corrections in log order; InputError naming what is missing."""
    log = folder / "session.mcap"
    if not log.is_file():
        raise InputError(f"{folder}: not a session folder (no session.mcap)")
    if not summarize(log).complete:
        raise InputError(f"{log}: truncated or corrupt (`octolog info {log}` shows what is readable)")
    items: list[KeyframeItem | CorrectionItem] = []
    for m in read_wire(log, [KEYFRAME.name, KEYFRAME_COMPRESSED.name, KEYFRAME_POSES.name]):
        msg = codec.decode(m.data, m.msgtype)
        stamp = codec.stamp_ns(msg.header)
        items.append(CorrectionItem(stamp, msg) if m.topic == KEYFRAME_POSES.name else KeyframeItem(stamp, int(msg.id), msg))
    if not any(isinstance(i, KeyframeItem) for i in items):
        raise InputError(f"{log}: no keyframes in it (a log without the tracker's output?)")
    return items


def _first_config(folder: Path, cfg: MapperConfig) -> MapperConfig:
    """The mapper config of the merge: `cfg` with the first session's map frame."""
    try:
        up = tomllib.loads((folder / "config.toml").read_text()).get("mapper", {}).get("grid_up")
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"{folder}: unreadable config.toml ({exc})") from None
    return dataclasses.replace(cfg, grid_up=up or cfg.grid_up)


def _prepare(out: Path, overwrite: bool) -> None:
    """An empty folder for the merged map; one a merge wrote before only with `overwrite`."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not (out / "map_stats.json").is_file():
            raise ConfigError(f"--out {out}: holds other files; give an empty or new folder")
        if not overwrite:
            raise ConfigError(f"--out {out}: holds a map; --overwrite replaces it")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


def merge_sessions(folders: list[Path], out: Path, cfg: MapperConfig | None = None, *, overwrite: bool = False) -> dict:
    """Merge the sessions in `folders` into `out` (map files, keyframe trajectories, map_stats.json);
    returns the stats."""
    if len(folders) < 2:
        raise InputError("give two sessions or more")
    names = tuple(f"session{i}" for i in range(len(folders)))
    streams = [session_items(f) for f in folders]  # all read before anything is written
    cfg = _first_config(folders[0], cfg or MapperConfig())
    _prepare(out, overwrite)
    # the sessions' keyframes come in turn: each one's confirm their own (mapper.confirm_within)
    mapper = make_mapper(dataclasses.replace(cfg, confirm_within=cfg.confirm_within * len(folders)))
    fleet = FleetMap(mapper, names, Placement.by_place(len(folders), cfg.relink_after_m))
    for i, item in merged_order(streams):
        fleet.apply(i, item)
    placement = fleet.placement
    unplaced = placement.unplaced()
    problems = list(fleet.problems)
    for r in unplaced:
        waiting = placement.take(r)
        where = write_separate_map(cfg, waiting, out / names[r])
        problems.append(f"{folders[r]}: never placed (no verified place shared with the map): its {len(waiting)} "
                        f"keyframes are in a map of their own, {where}")
    mapper.write(out)
    per_session = write_trajectories(mapper, names, fleet.trajectories, out)
    stats = {**mapper.stats(), "cloud_points": len(mapper.map_cloud()[0]),
             "sessions": {n: {"folder": str(f.resolve()), **per_session[n]} for n, f in zip(names, folders)},
             "merges": [merge_event(m, names) for m in placement.merges],
             "links": {kind: placement.link_kinds.count(kind) for kind in ("place", "refine", "relink")},
             "unmerged": [str(folders[r]) for r in unplaced], "problems": problems}
    (out / "map_stats.json").write_text(json.dumps(stats, indent=2, sort_keys=True) + "\n")
    return stats


def cmd_stitch(args: argparse.Namespace) -> int:
    """`octolog stitch`: the shards' tiles into one map; exit status 3 when a shard is missing."""
    out = Path(args.out)
    _prepare(out, args.overwrite)
    stats = stitch([Path(f) for f in args.shards], out)
    print(f"stitch: {len(stats['shards'])} shards -> {out}: {stats['occupied_voxels']} occupied voxels, "
          f"{stats['cloud_points']} cloud points")
    for problem in stats["problems"]:
        print(f"stitch: {problem}")
    return 3 if stats["missing_shards"] else 0

