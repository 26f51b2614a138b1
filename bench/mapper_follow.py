"""What a shard that follows the placement authority saves: the placing shard (the fleet's merge,
placement by shared places, joint graph, and its journal) against a follower (the journal's calls
only), on the same keyframes, and whether their maps are the same bytes.

Each SESSION is a folder of `octolog run`; its keyframes and corrections (the tracker's output) make
two robots, the second starting `--offset` items later (placed from a place the first saw, no start
poses). Both mappers are shard 2 of 2 (`--tile-m`), in this process, one after the other; CPU
seconds of the whole pass (process time), medians of `--repeat` passes.

    python bench/mapper_follow.py SESSION [SESSION ...] [--offset 5] [--tile-m 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.mapper.fleet.assembly import FleetMap
from octolog.mapper.fleet.journal import Journal, apply_op
from octolog.mapper.fleet.order import KeyframeItem, merged_order
from octolog.mapper.fleet.placement import Placement
from octolog.schemas import rgbdmsgs
from octolog.shell.merge import session_items

ROBOTS = ("r1", "r2")


def placing(cfg: MapperConfig, streams: list[list], out: Path) -> tuple[float, list[str], int]:
    """CPU s of the placing shard's pass, its journal lines, its keyframes."""
    mapper = make_mapper(cfg)
    journal = Journal(mapper, ROBOTS, lambda line: None)
    t = time.process_time()
    fm = FleetMap(mapper, ROBOTS, Placement.by_place(len(ROBOTS), cfg.relink_after_m), journal=journal)
    for i, item in merged_order(streams):
        fm.apply(i, item)
    mapper.write(out)
    journal.end({})
    return time.process_time() - t, journal.lines, fm.keyframes


def following(cfg: MapperConfig, streams: list[list], lines: list[str], out: Path) -> float:
    """CPU s of a follower's pass over the same keyframes and the journal."""
    kept = [{it.kf_id: it.payload for it in s if isinstance(it, KeyframeItem)} for s in streams]
    ops = [json.loads(line) for line in lines]
    t = time.process_time()
    mapper = make_mapper(cfg)
    for op in ops:
        if op["op"] == "up":
            mapper.set_up(tuple(op["up"]))
        apply_op(mapper, op, lambda r, k: rgbdmsgs.keyframe_from_msg(kept[r][k])[2])
    mapper.write(out)
    return time.process_time() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--offset", type=int, default=5)
    ap.add_argument("--tile-m", type=float, default=2.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cfg = MapperConfig(robots=ROBOTS, tile_m=args.tile_m, shard="2/2")
    print("| session | keyframes | placing shard, CPU ms per keyframe | follower | ratio | same bytes |")
    print("|---|---|---|---|---|---|")
    for session in args.sessions:
        items = session_items(session)
        streams = [items, items[args.offset:]]
        lead, follow, same = [], [], True
        for _ in range(args.repeat):
            with tempfile.TemporaryDirectory() as tmp:
                a, b = Path(tmp) / "placing", Path(tmp) / "following"
                s, lines, n = placing(cfg, streams, a)
                lead.append(s * 1e3 / n)
                follow.append(following(cfg, streams, lines, b) * 1e3 / n)
                same = same and all((a / f).read_bytes() == (b / f).read_bytes() for f in ("map.bt", "cloud.ply"))
        lm, fm = statistics.median(lead), statistics.median(follow)
        print(f"| {session.name} | {n} | {lm:.1f} | {fm:.1f} | {lm / fm:.2f}x | {'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main()
