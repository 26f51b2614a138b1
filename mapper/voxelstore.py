"""The occupancy map's voxels: packed keys, sorted and unique, with their log-odds and colour.

Two levels, so a scan's new voxels cost what the scan has, not what the map has: the main arrays,
and a small sorted level that takes the new keys. Inserting into one sorted array moves everything
after each insertion point, a copy of the whole map per scan (62 ms of a keyframe's 91 at 6.4
million voxels). The small level is merged into the main one once it holds `1/MERGE_FRACTION` of
it, so each voxel is moved a bounded number of times. Every key lives in exactly one level.

And in slabs: the voxels of each `SLAB_VOXELS` of x (3.2 m at 5 cm) are a two-level store of their
own. Packed keys sort x first, so the slabs in x order, each sorted, are the whole map sorted. A
scan touches the few slabs it sees: its binary searches run through those slabs, not through a
building's hundred million voxels, and a merge copies one slab. Readers get the slabs' merged
arrays side by side (`arrays`): the same arrays, so the same map bytes, as one sorted table gives.
"""

from __future__ import annotations

import numpy as np

from octolog.mapper.kernels import find_sorted, insert_sorted
from octolog.mapper.treebuild import WHITE  # OctoMap's "no colour"
# the new level is merged into the main one once it holds this fraction of it, or MERGE_MIN keys
MERGE_FRACTION = 8
MERGE_MIN = 1 << 16
SLAB_SHIFT = 32 + 6  # packed key >> SLAB_SHIFT: the slab (SLAB_VOXELS = 64 keys of x)


def _empty() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros((0, 3), np.uint8)


def _find(keys: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each of `wanted` is or would go in sorted `keys`, and whether it is there: a compiled
    walk for ascending `wanted` (mapper/kernels.py), a binary search per key otherwise."""
    if wanted.shape[0] < 2 or not np.any(wanted[1:] < wanted[:-1]):
        return find_sorted(keys, wanted)
    pos = np.searchsorted(keys, wanted)
    found = np.zeros(wanted.shape[0], dtype=bool)
    inside = pos < keys.shape[0]
    found[inside] = keys[pos[inside]] == wanted[inside]
    return pos, found


def _runs(keys: np.ndarray) -> list[tuple[int, int, int]]:
    """(slab, start, end) of each slab's run of sorted packed `keys`."""
    slab = keys >> SLAB_SHIFT
    cut = np.flatnonzero(slab[1:] != slab[:-1]) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [keys.shape[0]]])
    return [(int(slab[a]), int(a), int(b)) for a, b in zip(starts, ends)]


class VoxelStore:
    """Packed voxel keys with float32 log-odds and uint8 colour, in slabs of x (see the module)."""

    def __init__(self) -> None:
        self._slabs: dict[int, _Slab] = {}
        self._whole: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # `arrays`, until a change

    @classmethod
    def of(cls, keys: np.ndarray, logodds: np.ndarray, colours: np.ndarray) -> VoxelStore:
        """A store holding these voxels (keys sorted and unique)."""
        if keys.shape[0] > 1 and not np.all(keys[1:] > keys[:-1]):
            raise ValueError("voxel keys must be sorted and unique")
        store = cls()
        keys, logodds, colours = keys.astype(np.int64), logodds.astype(np.float32), colours.astype(np.uint8)
        for slab, a, b in (_runs(keys) if keys.shape[0] else []):
            store._slabs[slab] = _Slab()
            store._slabs[slab]._main = (keys[a:b].copy(), logodds[a:b].copy(), colours[a:b].copy())
        return store

    def __len__(self) -> int:
        return sum(len(s) for s in self._slabs.values())

    def copy(self) -> VoxelStore:
        """An independent copy (the slabs' arrays copied, their two levels as they are)."""
        store = VoxelStore()
        store._slabs = {k: slab.copy() for k, slab in self._slabs.items()}
        return store

    @property
    def nbytes(self) -> int:
        return sum(s.nbytes for s in self._slabs.values())

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keys, log-odds, colours), sorted by key, the slabs side by side (read-only use: kept
        until the next change)."""
        if self._whole is None:
            parts = [self._slabs[k].arrays() for k in sorted(self._slabs)]
            self._whole = tuple(np.concatenate([p[j] for p in parts]) for j in range(3)) if parts else _empty()
        return self._whole

    def update(self, keys: np.ndarray, delta: np.ndarray, lmin: float, lmax: float) -> None:
        """Add `delta` (float32) to the log-odds of sorted unique `keys`, clamped to [lmin, lmax];
        a key not in the map starts at 0 with no colour."""
        if keys.shape[0] == 0:
            return
        self._whole = None
        for slab, a, b in _runs(keys):
            self._slabs.setdefault(slab, _Slab()).update(keys[a:b], delta[a:b], lmin, lmax)

    def logodds_of(self, keys: np.ndarray) -> np.ndarray:
        """The log-odds (float32) of sorted unique `keys`; NaN (unknown) for keys not in the map."""
        out = np.full(keys.shape[0], np.nan, np.float32)
        for slab, a, b in (_runs(keys) if keys.shape[0] else []):
            if slab in self._slabs:
                out[a:b] = self._slabs[slab].logodds_of(keys[a:b])
        return out

    def average_colour(self, keys: np.ndarray, mean: np.ndarray) -> None:
        """OctoMap's averageNodeColor: each of `keys` (sorted, in the map) takes `mean` (int64),
        averaged with its colour if it has one."""
        if keys.shape[0] == 0:
            return
        self._whole = None
        for slab, a, b in _runs(keys):
            if slab in self._slabs:
                self._slabs[slab].average_colour(keys[a:b], mean[a:b])


class _Slab:
    """One slab's voxels in two levels (see the module)."""

    def __init__(self) -> None:
        self._main = _empty()
        self._new = _empty()

    def __len__(self) -> int:
        return int(self._main[0].shape[0] + self._new[0].shape[0])

    def copy(self) -> _Slab:
        slab = _Slab()
        slab._main = tuple(a.copy() for a in self._main)
        slab._new = tuple(a.copy() for a in self._new)
        return slab

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (*self._main, *self._new))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keys, log-odds, colours), one level, sorted by key."""
        self._merge()
        return self._main

    def update(self, keys: np.ndarray, delta: np.ndarray, lmin: float, lmax: float) -> None:
        """Add `delta` (float32) to the log-odds of sorted unique `keys`, clamped to [lmin, lmax];
        a key not in the map starts at 0 with no colour."""
        mk, ml, _ = self._main
        pos, found = _find(mk, keys)
        ml[pos[found]] = np.clip(ml[pos[found]] + delta[found], lmin, lmax).astype(np.float32)
        keys, delta = keys[~found], delta[~found]
        nk, nl, nc = self._new
        pos, found = _find(nk, keys)
        nl[pos[found]] = np.clip(nl[pos[found]] + delta[found], lmin, lmax).astype(np.float32)
        if not found.all():
            ins, at = ~found, pos[~found]
            fresh = np.clip(np.zeros(int(ins.sum()), np.float32) + delta[ins], lmin, lmax).astype(np.float32)
            self._new = insert_sorted(nk, nl, nc, at, keys[ins], fresh, WHITE)
        if self._new[0].shape[0] > max(MERGE_MIN, self._main[0].shape[0] // MERGE_FRACTION):
            self._merge()

    def logodds_of(self, keys: np.ndarray) -> np.ndarray:
        """The log-odds of sorted unique `keys` (NaN where absent)."""
        out = np.full(keys.shape[0], np.nan, np.float32)
        for level in (self._main, self._new):
            pos, found = _find(level[0], keys)
            out[found] = level[1][pos[found]]
        return out

    def average_colour(self, keys: np.ndarray, mean: np.ndarray) -> None:
        """OctoMap's averageNodeColor: each of `keys` (in the map) takes `mean` (int64), averaged
        with its colour if it has one."""
        for level in (self._main, self._new):
            pos, found = _find(level[0], keys)
            at = pos[found]
            prev = level[2][at].astype(np.int64)
            is_set = np.any(prev != WHITE, axis=1)
            level[2][at] = np.where(is_set[:, None], (prev + mean[found]) // 2, mean[found]).astype(np.uint8)
            keys, mean = keys[~found], mean[~found]

    def _merge(self) -> None:
        nk, nl, nc = self._new
        if nk.shape[0] == 0:
            return
        mk, ml, mc = self._main
        at = np.searchsorted(mk, nk)  # disjoint: every new key goes between main keys
        self._main = (np.insert(mk, at, nk), np.insert(ml, at, nl), np.insert(mc, at, nc, axis=0))
        self._new = _empty()
