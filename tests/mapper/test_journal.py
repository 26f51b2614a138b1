"""One placement authority for a sharded fleet map (mapper/fleet/journal.py), in-process: a shard
that follows the placing shard's journal builds the same bytes as one that places the robots itself,
the two stitch into the whole fleet map, and a journal that is damaged or cut short is refused. The
shards as processes on network-namespace hosts are in tests/shell/test_distributed.py."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from octolog.kit.errors import ConfigError, InputError
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.mapper.fleet.assembly import FleetMap
from octolog.mapper.fleet.journal import JOURNAL_FILE, Journal, apply_op, read_journal
from octolog.mapper.fleet.order import KeyframeItem, merged_order
from octolog.mapper.fleet.placement import Placement
from octolog.mapper.shards import stitch, write_shard
from octolog.schemas import rgbdmsgs
from octolog.shell.merge import session_items

ROBOTS = ("r1", "r2")
MAP_FILES = ("map.bt", "map.ot", "cloud.ply", "map.pgm")


@pytest.fixture(scope="module")
def streams(octolog_run) -> list[list]:
    """Two robots from one session log (the synthetic room): r1 all of it, r2 from its third item on,
    so r2 is placed by a place r1 saw; no start poses."""
    items = session_items(octolog_run("synthetic:40")[0])
    return [items, items[2:]]


def _fleet(cfg: MapperConfig, streams: list[list], out: Path, journal: bool = False,
           routed: set | None = None) -> Journal | None:
    """The fleet map of `streams` in the merge's order, placing the robots itself; its files. With
    `routed`, the (shard, robot, keyframe) its journal routes are added to it."""
    mapper = make_mapper(cfg)
    route = None if routed is None else (lambda k, r, kf: routed.add((k, r, kf)))
    j = Journal(mapper, ROBOTS, lambda line: None, route=route) if journal else None
    fm = FleetMap(mapper, ROBOTS, Placement.by_place(len(ROBOTS), cfg.relink_after_m), journal=j)
    for i, item in merged_order(streams):
        fm.apply(i, item)
    assert fm.placement.unplaced() == [], "r2 was not placed: the test shows nothing"
    if j is not None:
        j.end({"keyframes": fm.keyframes})
        out.mkdir(parents=True, exist_ok=True)
        j.write(out)
    mapper.write(out)
    if cfg.shard:
        write_shard(mapper, out)
    return j


def _follow(cfg: MapperConfig, streams: list[list], ops: list[dict], out: Path, routed: set | None = None) -> None:
    """A follower's map: the journal's ops, the robots' keyframes looked up by (robot, id); with
    `routed`, only those routed to its shard."""
    kept = [{item.kf_id: item.payload for item in s if isinstance(item, KeyframeItem)} for s in streams]
    shard = cfg.tiles().index if cfg.shard else 0

    def frame_of(r: int, k: int):
        assert routed is None or (shard, r, k) in routed, f"shard {shard} needs keyframe {k} of robot {r}: not routed"
        return rgbdmsgs.keyframe_from_msg(kept[r][k])[2]

    mapper = make_mapper(cfg)
    for op in ops:
        if op["op"] == "up":
            mapper.set_up(tuple(op["up"]))
        apply_op(mapper, op, frame_of)
    mapper.write(out)
    write_shard(mapper, out)


@pytest.fixture(scope="module")
def maps(streams, tmp_path_factory) -> Path:
    """The whole fleet map, shard 1/2 placing (its journal), shard 2/2 placing itself and following."""
    base = tmp_path_factory.mktemp("journal")
    cfg = MapperConfig(robots=ROBOTS, tile_m=2.0)
    _fleet(cfg, streams, base / "whole")
    _fleet(dataclasses.replace(cfg, shard="1/2"), streams, base / "s1", journal=True)
    _fleet(dataclasses.replace(cfg, shard="2/2"), streams, base / "s2-own")
    _follow(dataclasses.replace(cfg, shard="2/2", follow=f"journal:{base / 's1'}"), streams,
            read_journal(base / "s1"), base / "s2")
    return base


def test_a_follower_builds_the_bytes_of_a_shard_that_places_itself(maps):
    ops = read_journal(maps / "s1")
    kinds = {op["op"] for op in ops}
    assert {"start", "integrate", "correct", "end"} <= kinds, kinds  # r2's placement moved keyframes
    assert {op["robot"] for op in ops if op["op"] == "integrate"} == {0, 1}
    for name in (*MAP_FILES, "shard.npz"):
        assert (maps / "s2" / name).read_bytes() == (maps / "s2-own" / name).read_bytes(), name


def test_the_placing_shard_and_a_follower_stitch_into_the_whole_fleet_map(maps, tmp_path):
    stats = stitch([maps / "s1", maps / "s2"], tmp_path / "stitched")
    assert stats["missing_shards"] == [] and stats["problems"] == []
    for name in MAP_FILES:
        assert (tmp_path / "stitched" / name).read_bytes() == (maps / "whole" / name).read_bytes(), name


def test_keyframes_routed_to_the_shards_they_reach_build_the_whole_map(streams, maps, tmp_path):
    """Four shards of 16 m tiles: shard 1 places and routes each keyframe to the shards whose tiles
    it reaches; shards 2-4 make their maps from the journal and the routed keyframes alone (asking
    for another one fails the test). The stitch is the whole fleet map, and the routing spared a
    shard keyframes (the room reaches three of the four shards)."""
    cfg = MapperConfig(robots=ROBOTS, tile_m=16.0)
    routed: set = set()
    _fleet(dataclasses.replace(cfg, shard="1/4"), streams, tmp_path / "s1", journal=True, routed=routed)
    ops = read_journal(tmp_path / "s1")
    for k in (2, 3, 4):
        _follow(dataclasses.replace(cfg, shard=f"{k}/4"), streams, ops, tmp_path / f"s{k}", routed)
    stats = stitch([tmp_path / f"s{k}" for k in (1, 2, 3, 4)], tmp_path / "stitched")
    assert stats["missing_shards"] == [] and stats["problems"] == []
    for name in MAP_FILES:
        assert (tmp_path / "stitched" / name).read_bytes() == (maps / "whole" / name).read_bytes(), name
    integrated = sum(op["op"] == "integrate" for op in ops)
    per_shard = [sum(1 for k, _, _ in routed if k == shard) for shard in (2, 3, 4)]
    assert min(per_shard) < integrated and max(per_shard) > 0, (per_shard, integrated)


def test_a_journal_cut_short_or_damaged_is_refused(maps, tmp_path):
    lines = (maps / "s1" / JOURNAL_FILE).read_text().splitlines()
    (tmp_path / "cut").mkdir()
    (tmp_path / "cut" / JOURNAL_FILE).write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(InputError, match="ends early"):
        read_journal(tmp_path / "cut")
    (tmp_path / "bad.jsonl").write_text(lines[0] + "\n{not json\n")
    with pytest.raises(InputError, match="damaged placement journal"):
        read_journal(tmp_path / "bad.jsonl")
    with pytest.raises(InputError, match="no placement journal"):
        read_journal(tmp_path / "nowhere")
    first = json.loads(lines[0])
    assert first["robots"] == list(ROBOTS)


def test_follow_is_for_a_fleet_map():
    with pytest.raises(ConfigError, match="mapper.follow"):
        MapperConfig(follow="map/s1").validate()
