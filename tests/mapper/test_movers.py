"""Movers kept out of the map: a person stepping into space the map has seen free, and one who
stood and left. Made-up scans and frames (a wall, a patch in front of it); no ../shared needed."""

from __future__ import annotations

import dataclasses

import numpy as np

from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.mapper.voxelmap import VoxelOccupancyMap

K = Intrinsics(160, 120, 131.25, 131.25, 79.5, 59.5)


def _wall(x: float = 3.0) -> np.ndarray:
    g = np.arange(-0.5, 0.5, 0.02)
    y, z = np.meshgrid(g, g)
    return np.stack([np.full(y.size, x), y.ravel(), z.ravel()], 1)


def _with_patch(patch_x: float) -> np.ndarray:
    """The wall with a 20 cm patch at `patch_x` in front of it (the wall behind it hidden)."""
    wall = _wall()
    behind = (np.abs(wall[:, 1] - 0.1) < 0.1) & (np.abs(wall[:, 2] - 0.1) < 0.1)
    patch = wall[behind].copy()
    patch[:, 0] = patch_x
    return np.concatenate([wall[~behind], patch])


PATCH = np.array([[1.5, 0.11, 0.11]])  # a point inside the patch's voxels


def test_a_mover_in_space_seen_free_is_kept_out_until_it_stays():
    movers, origin = VoxelOccupancyMap(0.05, confirm_within=2), np.zeros(3)
    for _ in range(4):
        movers.insert(_wall(), origin)
    movers.insert(_with_patch(1.5), origin)
    assert movers.classify(PATCH)[0] == 0 and movers.masked.size > 0 and movers.masked_total == movers.masked.size
    assert movers.masked_centres()[:, 0].min() > 1.4 and movers.masked_centres()[:, 0].max() < 1.6
    assert movers.classify(_wall()[:5]).tolist() == [1] * 5  # the wall is no mover
    later = 0
    while movers.classify(PATCH)[0] != 1 and later < 20:  # it stays: seen again and again, it goes in
        movers.insert(_with_patch(1.5), origin)
        later += 1
        assert movers.masked.size == 0  # confirmed by the scan before: no longer a mover
    assert 2 < later < 20  # space seen free takes a few scans to fill


def test_an_end_point_counts_once_a_second_scan_confirms_it():
    m, octomap = VoxelOccupancyMap(0.05, confirm_within=2), VoxelOccupancyMap(0.05)
    side = _wall(1.5) + (0.0, 1.2, 0.0)  # beside the wall's rays: space no scan has seen
    here = np.array([[1.5, 1.2, 0.0]])
    for m_ in (m, octomap):
        m_.insert(_wall(), np.zeros(3))  # the first scan counts whole: nothing before it to confirm it
    assert m.classify(_wall()[:5]).tolist() == [1] * 5
    for scans in range(1, 3):
        for m_ in (m, octomap):
            m_.insert(np.concatenate([_wall(), side]), np.zeros(3))
        assert m.masked.size == 0  # nothing was seen free there: not a mover, a first sight
        assert m.classify(here)[0] == (-1 if scans == 1 else 1)  # unknown until confirmed
        assert octomap.classify(here)[0] == 1  # OctoMap: every end point at once
    behind = _wall(3.0) + (0.0, 2.4, 0.0)  # the person gone: the rays now pass where they stood
    m.insert(np.concatenate([_wall(), behind]), np.zeros(3))
    assert m.classify(here)[0] == 0  # one ray through a voxel only just confirmed undoes it


def _frame(seq: int, person: bool) -> RgbdFrame:
    depth = np.full((K.height, K.width), 3000, np.uint16)
    if person:
        depth[30:90, 60:100] = 1500
    rgb = np.full((K.height, K.width, 3), 90, np.uint8)
    return RgbdFrame(seq=seq, stamp_ns=seq * 250_000_000, rgb=rgb, depth=depth, depth_scale_m=0.001, intrinsics=K)


def _map(frames: list[bool], confirm_within: int):
    m = make_mapper(dataclasses.replace(MapperConfig(), confirm_within=confirm_within, full_keyframes_per_s=0.0))
    for i, person in enumerate(frames):
        m.integrate(i, np.eye(4), _frame(i, person))
    return m


def test_a_person_who_stood_and_left_leaves_no_trace_in_the_cloud():
    frames = [True] * 5 + [False] * 10  # stands in view for 5 keyframes, gone for the next 10
    on, off = _map(frames, 2), _map(frames, 0)
    depth_of = lambda pts: np.linalg.norm(pts - on.map_from_world[:3, 3], axis=1)  # noqa: E731
    raw = on.cloud.cloud()[0]
    assert (np.abs(depth_of(raw) - 1.5) < 0.1).sum() > 0  # the keyframes had the person
    assert (np.abs(depth_of(on.map_cloud()[0]) - 1.5) < 0.1).sum() == 0  # the map's cloud does not
    assert (np.abs(depth_of(off.map_cloud()[0]) - 1.5) < 0.1).sum() > 0  # off: the cloud is every keyframe's
    movers = on.stats()["movers"]
    assert movers["cleared_points"] > 0 and "movers" not in off.stats()


def test_a_person_walking_into_seen_space_is_masked_at_once():
    on = _map([False] * 4 + [True], 2)
    assert len(on.last_masked) > 0 and on.stats()["movers"]["masked_voxels"] == len(on.last_masked)
    assert on.octree.classify(on.last_masked).tolist() == [0] * len(on.last_masked)  # seen free, still free
