"""The occupancy map's two-level voxel store (mapper/voxelstore.py) against one plain sorted table."""

from __future__ import annotations

import numpy as np
import pytest

from octolog.mapper import voxelstore
from octolog.mapper.voxelstore import VoxelStore


@pytest.mark.parametrize("spread", [1, 1 << 35], ids=["one-slab", "many-slabs"])
def test_two_levels_hold_what_one_sorted_table_holds(monkeypatch, spread):
    """Scans of random keys (new ones and ones seen before), with hits, misses and colour, through
    merges of the small level (MERGE_MIN lowered so they happen often): after every scan the merged
    arrays, read now and then, equal a dict-based table updated the same way, bit for bit."""
    monkeypatch.setattr(voxelstore, "MERGE_MIN", 64)
    rng = np.random.default_rng(3)
    store, table, colour = VoxelStore(), {}, {}
    lmin, lmax = np.float32(-2.0), np.float32(3.5)
    for scan in range(40):
        keys = np.unique(rng.integers(0, 3000, rng.integers(1, 200))) * spread  # spread: x across slabs
        delta = rng.choice(np.array([0.85, -0.4], np.float32), keys.shape[0])
        store.update(keys, delta, lmin, lmax)
        for k, d in zip(keys.tolist(), delta):
            table[k] = np.clip(np.float32(table.get(k, np.float32(0.0))) + d, lmin, lmax).astype(np.float32)
        hit = keys[rng.random(keys.shape[0]) < 0.3]
        mean = rng.integers(0, 256, (hit.shape[0], 3))
        store.average_colour(hit, mean)
        for k, m in zip(hit.tolist(), mean):
            prev = colour.get(k)
            colour[k] = m if prev is None else (prev + m) // 2
        assert len(store) == len(table)
        if scan % 7 and scan != 39:
            continue  # the small level carries over to the next scans
        k_all, l_all, c_all = store.arrays()
        assert k_all.tolist() == sorted(table)
        assert np.array_equal(l_all, np.array([table[k] for k in sorted(table)], np.float32))
        want = np.array([colour.get(k, (255, 255, 255)) for k in sorted(table)], np.uint8)
        assert np.array_equal(c_all, want)


def test_the_compiled_lookup_is_a_binary_search():
    """mapper/kernels.py: find_sorted gives np.searchsorted's positions, and whether each key is
    there, for dense keys, sparse keys with gaps to gallop over, and keys beyond either end."""
    from octolog.mapper.kernels import find_sorted

    rng = np.random.default_rng(4)
    for n_keys, n_wanted, span in ((5000, 400, 20000), (5000, 50, 10**9), (0, 10, 100), (100, 0, 100)):
        keys = np.unique(rng.integers(0, span, n_keys))
        wanted = np.unique(np.concatenate([rng.choice(keys, min(len(keys), n_wanted // 2)) if len(keys) else [],
                                           rng.integers(-10, span + 10, n_wanted // 2)]).astype(np.int64))
        pos, found = find_sorted(keys, wanted)
        assert np.array_equal(pos, np.searchsorted(keys, wanted))
        assert np.array_equal(found, np.isin(wanted, keys))


def test_the_compiled_sorting_kernels_give_numpys_arrays():
    """mapper/kernels.py: unique_keys is np.unique with inverse and counts (keys of 1 to 40 bits,
    many repeats and none); merge_sorted is a stable argsort of the concatenation; insert_sorted is
    np.insert into the three arrays of a level; marked_keys packs the marked cells of a grid."""
    from octolog.mapper.kernels import insert_sorted, marked_keys, merge_sorted, unique_keys

    rng = np.random.default_rng(5)
    for n, bits in ((0, 8), (1, 1), (5000, 6), (20000, 23), (20000, 40)):
        keys = rng.integers(0, 2**bits, n)
        for got, want in zip(unique_keys(keys, bits), np.unique(keys, return_inverse=True, return_counts=True)):
            assert np.array_equal(got, want)
    a, b = np.unique(rng.integers(0, 10**6, 3000)), np.unique(rng.integers(0, 10**6, 2000))
    b = np.setdiff1d(b, a)
    va, vb = rng.random(len(a)).astype(np.float32), rng.random(len(b)).astype(np.float32)
    order = np.argsort(np.concatenate([a, b]), kind="stable")
    keys, vals = merge_sorted(a, va, b, vb)
    assert np.array_equal(keys, np.concatenate([a, b])[order]) and np.array_equal(vals, np.concatenate([va, vb])[order])
    colours = rng.integers(0, 255, (len(a), 3)).astype(np.uint8)
    at = np.searchsorted(a, b)
    got = insert_sorted(a, va, colours, at, b, vb, 255)
    white = np.full((len(b), 3), 255, np.uint8)
    want = (np.insert(a, at, b), np.insert(va, at, vb), np.insert(colours, at, white, axis=0))
    assert all(np.array_equal(g, w) for g, w in zip(got, want))
    shape, lo = np.array([7, 5, 9]), np.array([100, 200, 300])
    grid = (rng.random(int(np.prod(shape))) < 0.3).astype(np.uint8)
    x, y, z = np.unravel_index(np.flatnonzero(grid), tuple(shape))
    assert np.array_equal(marked_keys(grid, shape, lo), ((x + lo[0]) << 32) | ((y + lo[1]) << 16) | (z + lo[2]))
