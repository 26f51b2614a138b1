"""A map split into tiles across mapper shards (mapper/tiles.py) and stitched (mapper/shards.py):
the same bytes as one mapper, and a missing shard named, in-process. The shards as processes on
network-namespace hosts are in tests/shell/test_distributed.py."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from octolog.kit.errors import ConfigError, InputError
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.mapper.shards import SHARD_FILE, stitch, write_shard
from octolog.mapper.tiles import Tiles
from octolog.replay.synthetic import SyntheticScene

MAP_FILES = ("map.bt", "map.ot", "cloud.ply", "cloud.pcd", "map.pgm", "map.yaml")


@pytest.fixture(scope="module")
def keyframes():
    """Every 10th frame of the synthetic room's first 120, at ground-truth poses, and the same poses
    moved by a small rotation (a correction: the map is rebuilt)."""
    scene = SyntheticScene(n_frames=120)
    ids = range(0, 120, 10)
    frames = [scene.render(i) for i in ids]
    poses = [scene.pose(i) for i in ids]
    c, s = np.cos(0.01), np.sin(0.01)
    nudge = np.array([[c, 0, s, 0.02], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])
    return frames, poses, [nudge @ T for T in poses]


def _map(cfg: MapperConfig, keyframes, out):
    frames, poses, corrected = keyframes
    mapper = make_mapper(cfg)
    for k, (frame, pose) in enumerate(zip(frames, poses)):
        mapper.integrate(k, pose, frame)
    mapper.correct({k: T for k, T in enumerate(corrected) if k % 2})
    mapper.write(out)
    if cfg.shard:
        write_shard(mapper, out)
    return mapper


@pytest.mark.parametrize("count", [2, 3])
def test_shards_stitch_into_one_mappers_bytes(keyframes, tmp_path, count):
    """The room (6 x 5 m) in 2 m tiles over 2 and 3 shards, a correction included: every shard holds
    a part, and the stitched .bt, .ot, cloud and grid are byte for byte the single mapper's."""
    base = MapperConfig(tile_m=2.0)
    _map(base, keyframes, tmp_path / "one")
    shards = []
    for k in range(1, count + 1):
        mapper = _map(dataclasses.replace(base, shard=f"{k}/{count}"), keyframes, tmp_path / f"s{k}")
        assert mapper.octree.stats()["occupied_voxels"] > 0, f"shard {k} holds nothing of the room"
        shards.append(tmp_path / f"s{k}")
    stats = stitch(shards, tmp_path / "stitched")
    assert stats["missing_shards"] == [] and stats["problems"] == []
    for name in MAP_FILES:
        assert (tmp_path / "stitched" / name).read_bytes() == (tmp_path / "one" / name).read_bytes(), name
    whole = (tmp_path / "s1" / "map.bt").read_bytes()
    assert whole != (tmp_path / "one" / "map.bt").read_bytes()  # a shard's own map is its tiles only


def test_a_missing_shard_is_named_and_the_rest_written(keyframes, tmp_path):
    """Shard 2 of 2 never finished (no shard file): the stitch writes shard 1's tiles and names 2/2."""
    _map(MapperConfig(tile_m=2.0, shard="1/2"), keyframes, tmp_path / "s1")
    (tmp_path / "s2").mkdir()  # what a killed shard leaves: no shard file
    stats = stitch([tmp_path / "s1", tmp_path / "s2"], tmp_path / "out")
    assert stats["missing_shards"] == ["2/2"]
    assert any("s2" in p and SHARD_FILE in p for p in stats["problems"])
    assert any(p.startswith("shard 2/2 missing") for p in stats["problems"])
    assert (tmp_path / "out" / "map.bt").read_bytes() == (tmp_path / "s1" / "map.bt").read_bytes()


def test_shards_of_different_maps_are_refused(keyframes, tmp_path):
    _map(MapperConfig(tile_m=2.0, shard="1/2"), keyframes, tmp_path / "a")
    _map(MapperConfig(tile_m=4.0, shard="2/2"), keyframes, tmp_path / "b")
    with pytest.raises(InputError, match="tile_m"):
        stitch([tmp_path / "a", tmp_path / "b"], tmp_path / "out")


@pytest.mark.parametrize(("shard", "tile_m", "backend", "message"), [
    ("3/2", 8.0, "numpy", "1 <= K <= N"), ("half", 8.0, "numpy", "want K/N"),
    ("1/2", 0.125, "numpy", "whole number"), ("1/2", 8.0, "octomap", "numpy")])
def test_bad_shard_settings_say_what_is_wrong(shard, tile_m, backend, message):
    with pytest.raises(ConfigError, match=message):
        MapperConfig(shard=shard, tile_m=tile_m, backend=backend).validate()


def test_every_voxel_belongs_to_exactly_one_shard():
    """Random keys and points around tile borders: each is kept by exactly one of N shards."""
    rng = np.random.default_rng(5)
    packed = (rng.integers(32768 - 500, 32768 + 500, (5000, 3)) * np.array([1 << 32, 1 << 16, 1])).sum(axis=1)
    points = rng.uniform(-20, 20, (5000, 3))
    for n in (1, 2, 3, 5):
        tiles = [Tiles(k, n, 4.0, 0.05, 0.01) for k in range(1, n + 1)]
        assert np.all(sum(t.keep_packed(packed).astype(int) for t in tiles) == 1)
        assert np.all(sum(t.keep_points(points).astype(int) for t in tiles) == 1)


def test_a_shard_builds_clouds_only_for_keyframes_that_reach_its_tiles(keyframes, tmp_path):
    """The room laid down twice, 40 m apart, in 16 m tiles over four shards, then corrected (poses
    moved, the depth re-corrected): each shard makes the clouds of the keyframes that can reach its
    tiles only (a keyframe reaches 2 x 2 tiles here, so three shards of four), and the stitched map
    is still the single mapper's, byte for byte."""
    frames, poses, corrected = keyframes
    far = np.eye(4)
    far[0, 3] = 40.0
    twice = (frames + frames, poses + [far @ T for T in poses], corrected + [far @ T for T in corrected])
    outs, built = [], []
    for shard in ("", "1/4", "2/4", "3/4", "4/4"):
        mapper = make_mapper(MapperConfig(tile_m=16.0, shard=shard))
        for k, (frame, pose) in enumerate(zip(twice[0], twice[1])):
            mapper.integrate(k, pose, frame)
        mapper.correct({k: T for k, T in enumerate(twice[2]) if k % 3}, depth_inverse_offset=0.002)
        out = tmp_path / (shard.replace("/", "of") or "one")
        mapper.write(out)
        if shard:
            write_shard(mapper, out)
            outs.append(out)
        built.append(sum(kf.points_cam is not None for kf in mapper.keyframes.values()))
    assert built[0] == len(twice[0]) and sum(built[1:]) <= 3 * len(twice[0]), built
    stitch(outs, tmp_path / "stitched")
    for name in MAP_FILES:
        assert (tmp_path / "stitched" / name).read_bytes() == (tmp_path / "one" / name).read_bytes(), name
