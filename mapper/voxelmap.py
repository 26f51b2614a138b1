"""Own occupancy map: OctoMap's `insertPointCloud(..., discretize=True)` re-done in vectorised NumPy.

`VoxelOccupancyMap` keeps every known 5 cm voxel (no in-memory octree) as sorted packed int64 keys
with float32 log-odds, and reproduces OctoMap 1.10's arithmetic step by step so that the result is
the same tree, not just a similar one:

- keys: `floor(double(float(c)) * (1 / res)) + 32768` (16-level tree), as `coordToKey(point3d)`;
- end points: one per voxel, moved to the voxel centre as float32 (`computeDiscreteUpdate`);
- free space: Amanatides-Woo 3D DDA exactly as `computeRayKeys` (float32 direction and length,
  double `tMax`/`tDelta` accumulated sequentially, ties broken z > y > x, the origin voxel
  included, the end voxel excluded, stop when the voxel's exit distance exceeds the ray length);
  all rays advance together, one voxel per iteration, in NumPy;
- max range: centres farther than `max_range_m` give a ray cut at that range (float32
  `origin + dir.normalized() * (float) maxrange`) and no hit;
- each voxel updated once per scan, occupied winning over free; float32 `value += update`, then
  clamped to [logit(clamp_min), logit(clamp_max)]; occupied iff log-odds >= logit(occupancy_thres),
  as OctoMap (the sensor model: mapper/sensor_model.py).

Confirmed end points (`confirm_within` > 0, beyond OctoMap): a person walking by is hit by one
scan and gone by the next. An end point counts only when one of the `confirm_within` scans before
also hit that voxel, or the map holds it occupied already; until then its hit is left out (its ray
still clears the way to it). Until the voxel is occupied, a confirmed hit is three quarters of a
miss: one ray through it undoes the first (a person who paused for two scans), and space seen free
takes a few scans to fill (a person standing for a moment). A surface that stays is seen again by
the next scans and goes in; a person who stood still and left is cleared by the rays that now pass
through where they stood. Every end point of the map's first scan counts (nothing came before it
to confirm it: a camera on a tripod makes one keyframe). Unconfirmed hits in voxels the map holds
free are movers, something that appeared in space seen empty: the last scan's (`masked`) and their
count over all scans (`masked_total`) are kept for the viewer and the summary.

Colour follows `ColorOcTree::averageNodeColor`, applied once per scan and voxel: the scan's mean
colour of the points in an occupied end-point voxel (rounded half to even) is averaged with the
previous colour as `(prev + new) // 2`; (255, 255, 255) means "no colour" as in OctoMap.

Output is serialised by building the pruned octree from the voxels (vectorised, level by level):
`.bt` after max-likelihood + pruning (OctoMap's `writeBinary`), `.ot` as OcTree (log-odds, pruned
where 8 siblings have equal log-odds, exactly the tree OctoMap holds in memory) or as ColorOcTree
(pruned only where value *and* colour agree, so colours survive; inner colours are OctoMap's
average of the children's set colours).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from octolog.kit.errors import MapError
from octolog.kit.files import write_bytes_atomic
from octolog.mapper.octokeys import TREE_MAX_VAL, key_to_coord, norm32, pack, to_key, unpack
from octolog.mapper.cloud import column_max, column_min, rows_where
from octolog.mapper.kernels import accumulate_rows, find_sorted, marked_keys, merge_sorted, walk_rays
from octolog.mapper.sensor_model import SensorModel
from octolog.mapper.voxelstore import VoxelStore
from octolog.mapper.treebuild import build_tree

__all__ = ["Region", "VoxelOccupancyMap"]


class Region(Protocol):
    """The voxels a map keeps (mapper.tiles.Tiles: a shard's tiles)."""

    def keep_packed(self, packed: np.ndarray) -> np.ndarray: ...

    def touches_keys(self, lo: np.ndarray, hi: np.ndarray) -> bool: ...

_DBL_MAX = float(np.finfo(np.float64).max)
_NO_KEYS = np.zeros(0, np.int64)
_DENSE_MAX_CELLS = 1 << 26  # per-scan scratch grid limit (64 MiB of uint8), beyond it use np.unique
_RAY_CHUNK = 65536  # rays per DDA batch: caps its working arrays (~100 bytes a ray) at a few MB


def _no_scan() -> None:
    """insert_all's stand-in for a scan that reaches none of the map (`elsewhere`)."""
    return None


@dataclass(frozen=True)
class _Scan:
    """One scan's updates (VoxelOccupancyMap._scan): packed free and occupied keys, sorted, and the
    occupied end points' (packed keys, mean colours) when coloured."""

    free: np.ndarray
    occ: np.ndarray
    colour: tuple[np.ndarray, np.ndarray] | None


@dataclass(frozen=True)
class Checkpoint:
    """A VoxelOccupancyMap's whole state (`checkpoint`): its voxels, the recent scans' end points
    that confirm hits, the masked end points."""

    store: VoxelStore
    recent: list[np.ndarray]
    masked: np.ndarray
    masked_total: int


BT_HEADER = "# Octomap OcTree binary file"
OT_HEADER = "# Octomap OcTree file"
_COMMENT = "\n# (feel free to add / change comments, but leave the first line as it is!)\n#\n"


class _ScanGrid:
    """Per-scan de-duplication of voxel keys: a dense uint8 grid over the scan's key box."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, *, alloc: bool = True) -> None:
        self.lo = lo.astype(np.int64)
        self.shape = (hi - lo + 1).astype(np.int64)
        ny, nz = int(self.shape[1]), int(self.shape[2])
        self.strides = np.array([ny * nz, nz, 1], dtype=np.int64)
        self.cells = int(np.prod(self.shape))
        self.dense = self.cells <= _DENSE_MAX_CELLS
        self.grid = np.zeros(self.cells, dtype=np.uint8) if (self.dense and alloc) else None
        self._free: list[np.ndarray] = []

    def lin(self, keys: np.ndarray) -> np.ndarray:
        """Linear indices of (N,3) keys in the scan's key box."""
        s0, s1 = int(self.strides[0]), int(self.strides[1])
        lo = self.lo
        return (keys[:, 0] - lo[0]) * s0 + (keys[:, 1] - lo[1]) * s1 + (keys[:, 2] - lo[2])

    def mark_free(self, lin: np.ndarray) -> None:
        """Mark the voxels at linear indices `lin` as passed by a ray."""
        if self.dense:
            self.grid[lin] = 1
        else:
            self._free.append(lin.copy())

    def result(self, occ_lin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free, occupied) packed keys, each sorted and unique, disjoint (occupied wins)."""
        if occ_lin.shape[0] > 1 and not np.all(occ_lin[1:] > occ_lin[:-1]):  # voxel centres' keys come sorted
            occ_lin = np.unique(occ_lin)
        if self.dense:  # the marked cells in the grid's order are sorted packed keys already
            self.grid[occ_lin] = 0
            return marked_keys(self.grid, self.shape, self.lo), self._to_packed(occ_lin)
        free_lin = np.unique(np.concatenate(self._free)) if self._free else np.zeros(0, np.int64)
        free_lin = free_lin[~np.isin(free_lin, occ_lin, assume_unique=True)]
        return self._to_packed(free_lin), self._to_packed(occ_lin)

    def _to_packed(self, lin: np.ndarray) -> np.ndarray:
        ny, nz = int(self.shape[1]), int(self.shape[2])
        x, rem = np.divmod(lin, ny * nz)
        y, z = np.divmod(rem, nz)
        return ((x + self.lo[0]) << 32) | ((y + self.lo[1]) << 16) | (z + self.lo[2])


def _dda_start(origin32: np.ndarray, ends32: np.ndarray, ko: np.ndarray, res: float) -> tuple[np.ndarray, ...]:
    """Each ray's length, voxel step and first boundary distances (`tMax`, `tDelta`), as computeRayKeys."""
    direction = ends32 - origin32  # float32
    length = norm32(direction).astype(np.float32)
    direction = direction / length[:, None]  # float32 division, as Vector3::operator/=
    length = length.astype(np.float64)
    step = np.sign(direction).astype(np.int64)
    dir64 = direction.astype(np.float64)
    half = (step.astype(np.float64) * res * 0.5).astype(np.float32).astype(np.float64)
    border = key_to_coord(ko, res)[None, :] + half
    with np.errstate(divide="ignore", invalid="ignore"):
        t_max = np.where(step != 0, (border - origin32.astype(np.float64)[None, :]) / dir64, _DBL_MAX)
        t_delta = np.where(step != 0, res / np.abs(dir64), _DBL_MAX)
    return length, step, t_max, t_delta


def _cast_rays(grid: _ScanGrid, origin32: np.ndarray, ends32: np.ndarray, res: float) -> None:
    """OctoMap `computeRayKeys(origin, end)` for all rays at once; marks the ray voxels in `grid`."""
    rf = 1.0 / res
    ko = to_key(origin32[None, :], rf)[0]
    ke = to_key(ends32, rf)
    moving = np.any(ke != ko, axis=1)  # same cell: OctoMap adds nothing, not even the origin
    if not moving.any():
        return
    ends32, ke = ends32[moving], ke[moving]
    grid.mark_free(grid.lin(ko[None, :]))

    length, step, t_max, t_delta = _dda_start(origin32, ends32, ko, res)
    n_steps = np.abs(ke - ko).sum(axis=1)
    if grid.dense:  # compiled, a ray at a time (mapper/kernels.py)
        if not walk_rays(t_max, t_delta, step * grid.strides[None, :], length, int(grid.lin(ko[None, :])[0]),
                         grid.lin(ke), grid.grid, int(n_steps.max()) + 8):
            raise MapError("ray casting did not terminate (inconsistent ray geometry)")
        return

    # Longest rays first, so finished rays are mostly a suffix and the live set is a slice.
    order = np.argsort(-n_steps, kind="stable")
    lin_step = (step * grid.strides[None, :])[order]
    tx, ty, tz = (np.ascontiguousarray(t_max[order, i]) for i in range(3))
    dx, dy, dz = (np.ascontiguousarray(t_delta[order, i]) for i in range(3))
    sx, sy, sz = (np.ascontiguousarray(lin_step[:, i]) for i in range(3))
    length = length[order]
    lin_end = grid.lin(ke[order])
    lin = np.full(tx.shape[0], int(grid.lin(ko[None, :])[0]), dtype=np.int64)

    max_iter = int(n_steps.max()) + 8
    for _ in range(max_iter):
        c01 = tx < ty
        d0 = c01 & (tx < tz)
        d1 = ~c01 & (ty < tz)
        d2 = ~(d0 | d1)
        np.add(tx, dx, out=tx, where=d0)
        np.add(ty, dy, out=ty, where=d1)
        np.add(tz, dz, out=tz, where=d2)
        np.add(lin, sx, out=lin, where=d0)
        np.add(lin, sy, out=lin, where=d1)
        np.add(lin, sz, out=lin, where=d2)
        dist = np.minimum(np.minimum(tx, ty), tz)
        keep = (lin != lin_end) & ~(dist > length)
        n_keep = int(np.count_nonzero(keep))
        if n_keep == 0:
            break
        if n_keep == keep.shape[0]:
            grid.mark_free(lin)
            continue
        if keep[:n_keep].all():  # finished rays form a suffix: slice, no copies
            sl = slice(0, n_keep)
            tx, ty, tz, dx, dy, dz = tx[sl], ty[sl], tz[sl], dx[sl], dy[sl], dz[sl]
            sx, sy, sz, length, lin_end, lin = sx[sl], sy[sl], sz[sl], length[sl], lin_end[sl], lin[sl]
        else:
            tx, ty, tz, dx, dy, dz = tx[keep], ty[keep], tz[keep], dx[keep], dy[keep], dz[keep]
            sx, sy, sz = sx[keep], sy[keep], sz[keep]
            length, lin_end, lin = length[keep], lin_end[keep], lin[keep]
        grid.mark_free(lin)
    else:
        raise MapError("ray casting did not terminate (inconsistent ray geometry)")


def _endpoint_voxels(box: _ScanGrid, keys: np.ndarray, with_inverse: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Sorted unique linear indices of the end-point voxels, and each point's index among them."""
    plin = box.lin(keys)
    if box.dense:
        mark = np.zeros(box.cells, dtype=bool)
        mark[plin] = True
        ulin = np.flatnonzero(mark)
        inverse = None
        if with_inverse:
            lookup = np.empty(box.cells, dtype=np.int64)
            lookup[ulin] = np.arange(ulin.shape[0])
            inverse = lookup[plin]
        del mark
    else:
        ulin, inverse = np.unique(plin, return_inverse=True)
    return ulin, inverse


class VoxelOccupancyMap:
    """Sparse occupancy voxels with OctoMap's sensor model; OctoMap-compatible `.bt` / `.ot` output."""

    backend = "numpy"

    def __init__(self, resolution: float = 0.05, *, model: SensorModel = SensorModel(), colour: bool = True,
                 region: Region | None = None, confirm_within: int = 0) -> None:
        model.check(resolution)
        if confirm_within < 0:
            raise MapError(f"confirm_within must be >= 0 (0: off), got {confirm_within}")
        self.resolution = float(resolution)
        self.region = region  # a shard's tiles (mapper.tiles): only their voxels are kept
        self.model = model
        self.colour = bool(colour)
        lo = model.logodds()
        self._hit = lo.hit
        self._miss = lo.miss
        self._lmin = lo.clamp_min
        self._lmax = lo.clamp_max
        self._thres = lo.occupancy_thres
        self.confirm_within = int(confirm_within)  # see the module; 0: every end point counts (OctoMap)
        # a confirmed hit in a voxel not occupied yet: three quarters of a miss (see the module)
        self._confirming = np.float32(-0.75 * self._miss)
        self.clear()

    def clear(self) -> None:
        """Forget everything (e.g. before re-integrating keyframes after a loop closure)."""
        self._store = VoxelStore()  # packed keys sorted and unique, log-odds, colour (255,255,255: none)
        self._recent: list[np.ndarray] = []  # the last `confirm_within` scans' end-point voxels
        self.masked = np.zeros(0, np.int64)  # the last scan's masked end-point voxels, packed
        self.masked_total = 0

    def checkpoint(self) -> Checkpoint:
        """The map's whole state now (a copy): `restore` brings it back, so re-inserting the scans
        that followed gives the same bytes as if it had never left."""
        return Checkpoint(self._store.copy(), list(self._recent), self.masked.copy(), self.masked_total)

    def restore(self, cp: Checkpoint) -> None:
        """Return to the state of `checkpoint` (which stays as it is, for another return)."""
        self._store, self._recent = cp.store.copy(), list(cp.recent)
        self.masked, self.masked_total = cp.masked.copy(), cp.masked_total

    def voxels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every known voxel: packed keys (sorted), log-odds, colours (copies)."""
        return tuple(a.copy() for a in self._store.arrays())

    def set_voxels(self, packed: np.ndarray, logodds: np.ndarray, colours: np.ndarray) -> None:
        """Replace the map by these voxels (packed keys sorted and unique), e.g. tiles stitched together."""
        self._store = VoxelStore.of(packed, logodds, colours)

    @property
    def _keys(self) -> np.ndarray:
        return self._store.arrays()[0]

    @property
    def _logodds(self) -> np.ndarray:
        return self._store.arrays()[1]

    @property
    def _rgb(self) -> np.ndarray:
        return self._store.arrays()[2]

    # ---- integration ----------------------------------------------------------------------------

    def insert(
        self,
        points_world: np.ndarray,
        origin: np.ndarray,
        *,
        colours: np.ndarray | None = None,
        max_range_m: float = -1.0,
        discretize: bool = True,
    ) -> int:
        """Integrate one scan: end-point voxels hit, voxels on the rays from `origin` missed.

        `max_range_m` < 0 means unlimited; longer rays are cut there and only mark free space.
        `colours` (N,3) uint8 colour the occupied end-point voxels (see module docstring).
        `discretize=False` casts rays to the raw points (OctoMap's default) instead of voxel centres.
        Returns the number of points given.
        """
        scan = self._cast(points_world, origin, colours, max_range_m, discretize)
        self._commit(scan)
        return int(np.shape(points_world)[0])

    def _cast(self, points_world: np.ndarray, origin: np.ndarray, colours: np.ndarray | None, max_range_m: float,
              discretize: bool) -> _Scan | None:
        """`insert`'s checks of its arguments, then the scan's updates (`_scan`); None: nothing to add."""
        pts = np.asarray(points_world)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MapError(f"octree points must have shape (N, 3), got {pts.shape}")
        org = np.asarray(origin, dtype=np.float64).reshape(-1)
        if org.shape != (3,):
            raise MapError(f"sensor origin must have 3 coordinates, got shape {np.shape(origin)}")
        if not np.isfinite(org).all():
            raise MapError("sensor origin contains NaN or infinite values")
        if pts.shape[0] and not np.isfinite(pts_range := np.array([pts.min(), pts.max()])).all():
            raise MapError("octree points contain NaN or infinite coordinates")
        if not np.isfinite(max_range_m) or max_range_m == 0:
            raise MapError(f"max_range_m must be > 0 (or negative for unlimited), got {max_range_m}")
        if colours is not None:
            colours = np.asarray(colours)
            if colours.shape != pts.shape or colours.dtype != np.uint8:
                raise MapError(f"colours must be ({pts.shape[0]}, 3) uint8, got {colours.shape} {colours.dtype}")
        limit = TREE_MAX_VAL * self.resolution
        if pts.shape[0] == 0:
            return None
        if np.abs(pts_range).max() >= limit or np.abs(org).max() >= limit:
            raise MapError(f"points outside the octree's addressable cube of +/-{limit:g} m")
        return self._scan(pts, org, colours, float(max_range_m), bool(discretize))

    def insert_all(self, scans: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray | None] | None], *,
                   max_range_m: float = -1.0, committed: Callable[[], None] | None = None) -> None:
        """`insert(points, origin, colours=colours, max_range_m=...)` of each (points, origin, colours)
        in order (a rebuild; None: `elsewhere()`), `committed()` after each. The rays of the next scan
        are cast on a second thread while this one's updates go in: the cast is pure (compiled, without
        the GIL) and the updates keep their order, so the map is the same bytes as from one `insert`
        after another."""
        with ThreadPoolExecutor(1, thread_name_prefix="voxelmap-rays") as pool:
            ahead: Callable[[], _Scan | None] | None = None  # the scan cast ahead, committed next
            for item in scans:
                nxt = pool.submit(self._cast, *item, max_range_m, True).result if item is not None else _no_scan
                if ahead is not None:
                    self._commit(ahead())
                    if committed is not None:
                        committed()
                ahead = nxt
            if ahead is not None:
                self._commit(ahead())
                if committed is not None:
                    committed()

    def elsewhere(self) -> None:
        """A scan that reaches none of this map (a shard's keyframe away from its tiles): it counts
        among the recent scans an end point is confirmed by, as it does in the whole map."""
        self._commit(None)

    def _scan(self, pts: np.ndarray, org: np.ndarray, colours: np.ndarray | None,
              max_range: float, discretize: bool) -> _Scan | None:
        """One scan's updates, from the scan alone (nothing of the map is read or changed): its free
        and occupied voxels and, with `colours`, their colours; None when no ray reaches the region."""
        res = self.resolution
        rf = 1.0 / res
        p32 = pts.astype(np.float32)
        o32 = org.astype(np.float32)
        keys = to_key(p32, rf)
        ko = to_key(o32[None, :], rf)[0]
        lo = np.minimum([keys[:, i].min() for i in range(3)], ko)
        hi = np.maximum([keys[:, i].max() for i in range(3)], ko)
        if lo.min() < 0 or hi.max() >= 2 * TREE_MAX_VAL:
            raise MapError(f"points outside the octree's addressable cube of +/-{TREE_MAX_VAL * res:g} m")

        # Unique end-point voxels (and each point's voxel, for colour).
        box = _ScanGrid(lo, hi, alloc=False)
        ulin, inverse = _endpoint_voxels(box, keys, colours is not None)
        ukeys = unpack(box._to_packed(ulin))

        if discretize:
            ends = key_to_coord(ukeys, res).astype(np.float32)
        else:
            ends = p32
        dist = norm32(ends - o32[None, :])
        in_range = np.ones(ends.shape[0], dtype=bool) if max_range < 0 else dist <= max_range
        if not in_range.all():
            far = ~in_range
            d = ends[far] - o32[None, :]
            d = d / dist[far].astype(np.float32)[:, None]  # normalized(): divide by (float) norm
            ends = ends.copy()
            ends[far] = o32[None, :] + d * np.float32(max_range)
        if discretize:
            occ_sel = in_range  # per unique voxel
            occ_keys = ukeys[occ_sel]
        else:
            occ_keys = keys[in_range]

        # Ray end voxels may lie outside the points' box (rays cut at max range stay inside it).
        ray_keys = to_key(ends, rf)
        glo = np.minimum(lo, column_min(ray_keys))
        ghi = np.maximum(hi, column_max(ray_keys))
        # Pad one voxel: the DDA never leaves the segment's key box, but be safe at borders.
        if self.region is not None and not self.region.touches_keys(glo - 1, ghi + 1):
            return None  # no ray of this scan reaches the shard's tiles
        grid = _ScanGrid(glo - 1, ghi + 1)
        for s in range(0, ends.shape[0], _RAY_CHUNK):
            _cast_rays(grid, o32, ends[s:s + _RAY_CHUNK], res)
        free, occ = grid.result(grid.lin(occ_keys))
        if self.region is not None:
            free, occ = free[self.region.keep_packed(free)], occ[self.region.keep_packed(occ)]
        colour = None
        if colours is not None and occ.shape[0]:
            colour = self._scan_colour(colours, inverse, ulin, in_range, box, keys, discretize)
        return _Scan(free, occ, colour)

    def _commit(self, scan: _Scan | None) -> None:
        """A scan's updates into the map: the misses and the (confirmed, see the module) hits, then
        the colours. None: a scan with nothing here (it is still one of the recent scans)."""
        if scan is None:
            if self.confirm_within:
                self._recent = [_NO_KEYS, *self._recent[:self.confirm_within - 1]]
            return
        occ, hits, colour = scan.occ, None, scan.colour
        if self.confirm_within:
            occ, hits, colour = self._confirmed(scan)
        self._apply_updates(scan.free, occ, hits)
        if colour is not None:
            self._store.average_colour(*colour)

    def _confirmed(self, scan: _Scan) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """The scan's end-point voxels whose hits count (see the module), each one's hit, and their
        colours."""
        occ = scan.occ
        before = self._store.logodds_of(occ)
        occupied = before >= self._thres
        ok = occupied.copy() if self._recent else np.ones(occ.shape[0], bool)  # the first scan: none to wait for
        for earlier in self._recent:
            ok |= find_sorted(earlier, occ)[1]
        self._recent = [occ, *self._recent[:self.confirm_within - 1]]
        self.masked = occ[~ok & (before < 0)]
        self.masked_total += int(self.masked.shape[0])
        hits = np.where(occupied, self._hit, self._confirming).astype(np.float32)
        colour = scan.colour
        if ok.all():
            return occ, hits, colour
        if colour is not None:
            kept = find_sorted(occ[ok], colour[0])[1]  # both sorted and unique
            colour = (colour[0][kept], colour[1][kept])
        return occ[ok], hits[ok], colour

    def masked_centres(self) -> np.ndarray:
        """The centres (N, 3) of the last scan's masked end-point voxels."""
        return key_to_coord(unpack(self.masked), self.resolution)

    def _apply_updates(self, free: np.ndarray, occ: np.ndarray, hits: np.ndarray | None = None) -> None:
        """Free cells get the miss update, occupied cells the hit update (`hits`, each its own, or the
        model's), once per scan, clamped."""
        keys, upd = merge_sorted(free, np.full(free.shape[0], self._miss, np.float32),
                                 occ, np.full(occ.shape[0], self._hit, np.float32) if hits is None else hits)
        self._store.update(keys, upd, self._lmin, self._lmax)

    def _scan_colour(self, colours: np.ndarray, inverse: np.ndarray, ulin: np.ndarray, in_range: np.ndarray,
                     box: _ScanGrid, keys: np.ndarray, discretize: bool) -> tuple[np.ndarray, np.ndarray]:
        """The scan's mean colour of each occupied end-point voxel (packed keys, colours), for
        averageNodeColor."""
        m = ulin.shape[0]
        pt_ok = in_range[inverse] if discretize else in_range
        idx = inverse[pt_ok]
        cnt = np.bincount(idx, minlength=m)
        has = cnt > 0
        mean = np.zeros((m, 3), dtype=np.float64)
        accumulate_rows(idx, 0, rows_where(colours, pt_ok), mean)  # np.bincount's sums, one pass
        mean = np.clip(np.rint(mean[has] / cnt[has, None]), 0, 255).astype(np.int64)
        packed = box._to_packed(ulin[has])
        if self.region is not None:
            mine = self.region.keep_packed(packed)
            packed, mean = packed[mine], mean[mine]
        return packed, mean

    # ---- queries -------------------------------------------------------------------------------

    def keys(self) -> np.ndarray:
        """Known voxel keys (N,3) int64, sorted by (x, y, z)."""
        return unpack(self._keys)

    def logodds_values(self) -> np.ndarray:
        """Log-odds (N,) float32 of the known voxels, in `keys()` order."""
        return self._logodds.copy()

    def colours(self) -> np.ndarray:
        """Colour (N,3) uint8 of the known voxels in `keys()` order; (255,255,255) = none."""
        return self._rgb.copy()

    def occupied_mask(self) -> np.ndarray:
        """Per known voxel (in `keys()` order): log-odds at or above the occupancy threshold."""
        return self._logodds >= self._thres

    def _centres(self, want_occupied: bool, max_voxels: int | None) -> np.ndarray:
        sel = self.occupied_mask() == want_occupied
        n = int(sel.sum())
        if max_voxels is not None and n > max_voxels:
            raise MapError(f"{n} voxels exceed max_voxels={max_voxels}")
        return key_to_coord(unpack(self._keys[sel]), self.resolution)

    def occupied_centres(self, max_voxels: int | None = None) -> np.ndarray:
        """Centres (N,3) of occupied voxels, sorted by (x, y, z) index."""
        return self._centres(True, max_voxels)

    def free_centres(self, max_voxels: int | None = None) -> np.ndarray:
        """Centres (N,3) of free voxels, sorted by (x, y, z) index."""
        return self._centres(False, max_voxels)

    def band_centres(self, z_min: float, z_max: float) -> tuple[np.ndarray, np.ndarray]:
        """Centres (N,3) of the occupied and of the free voxels whose centre's z is in [z_min, z_max],
        each sorted by (x, y, z) index."""
        keys, logodds = self._keys, self._logodds
        z = key_to_coord(keys & 0xFFFF, self.resolution)
        band = (z >= z_min) & (z <= z_max)
        occupied = logodds >= self._thres
        return tuple(key_to_coord(unpack(keys[band & sel]), self.resolution) for sel in (occupied, ~occupied))

    def occupied_colours(self) -> np.ndarray:
        """Colours (N,3) uint8 of `occupied_centres()`."""
        return self._rgb[self.occupied_mask()].copy()

    def classify(self, points: np.ndarray) -> np.ndarray:
        """Per point: 1 occupied, 0 free, -1 unknown (int8)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MapError(f"query points must have shape (N, 3), got {pts.shape}")
        out = np.full(pts.shape[0], -1, dtype=np.int8)
        if pts.shape[0] == 0 or self._keys.shape[0] == 0:
            return out
        k = to_key(pts.astype(np.float32), 1.0 / self.resolution)
        ok = np.all((k >= 0) & (k < 2 * TREE_MAX_VAL), axis=1)
        packed = pack(np.clip(k, 0, 2 * TREE_MAX_VAL - 1))
        pos = np.clip(np.searchsorted(self._keys, packed), 0, self._keys.shape[0] - 1)
        hit = ok & (self._keys[pos] == packed)
        out[hit] = np.where(self._logodds[pos[hit]] >= self._thres, 1, 0)
        return out

    def stats(self) -> dict:
        """Counts and volumes, as `OccupancyOctree.stats()`; leaves are full-resolution voxels here."""
        occ = self.occupied_mask()
        occ_vox = int(occ.sum())
        free_vox = int(occ.shape[0] - occ_vox)
        v1 = self.resolution**3
        return {
            "resolution_m": self.resolution,
            "occupied_leaves": occ_vox,
            "free_leaves": free_vox,
            "occupied_voxels": occ_vox,
            "free_voxels": free_vox,
            "occupied_volume_m3": occ_vox * v1,
            "free_volume_m3": free_vox * v1,
            "known_volume_m3": (occ_vox + free_vox) * v1,
            "num_nodes": int(occ.shape[0]),
            "memory_bytes": self._store.nbytes,
        }

    # ---- serialisation -------------------------------------------------------------------------

    def _header(self, first_line: str, tree_id: str, size: int) -> bytes:
        res = f"{self.resolution:g}"  # C++ ostream default: 6 significant digits
        return (f"{first_line}{_COMMENT}id {tree_id}\nsize {size}\nres {res}\ndata\n").encode("ascii")

    def bt_bytes(self) -> bytes:
        """OctoMap binary `.bt`: max-likelihood, pruned, 2 bits per child, depth first."""
        occ = self.occupied_mask()
        tree = build_tree(self.keys(), occ.astype(np.int64), self._logodds, occ, None)
        head = self._header(BT_HEADER, "OcTree", tree.size)
        if tree.size == 0:
            return head
        inner = ~tree.leaf
        return head + tree.bt_bits[inner].astype("<u2").tobytes()

    def ot_bytes(self, *, colour: bool | None = None) -> bytes:
        """OctoMap `.ot` (full log-odds): ColorOcTree if `colour` (default: the map's flag), else OcTree."""
        colour = self.colour if colour is None else bool(colour)
        vals = self._logodds
        bits = vals.view(np.int32).astype(np.int64)
        if colour:
            rgb = self._rgb.astype(np.int64)
            prune_key = (bits << 24) | (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
            tree = build_tree(self.keys(), prune_key, vals, self.occupied_mask(), self._rgb)
        else:
            tree = build_tree(self.keys(), bits, vals, self.occupied_mask(), None)
        head = self._header(OT_HEADER, "ColorOcTree" if colour else "OcTree", tree.size)
        if tree.size == 0:
            return head
        if colour:
            rec = np.empty(tree.size, dtype=[("v", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1"), ("c", "u1")])
            rec["r"], rec["g"], rec["b"] = tree.rgb[:, 0], tree.rgb[:, 1], tree.rgb[:, 2]
        else:
            rec = np.empty(tree.size, dtype=[("v", "<f4"), ("c", "u1")])
        rec["v"] = tree.value
        rec["c"] = tree.child_mask
        return head + rec.tobytes()

    def write_bt(self, path: str | os.PathLike[str]) -> None:
        """Write the `.bt` file atomically (temporary file then rename)."""
        write_bytes_atomic(Path(path), self.bt_bytes())

    def write_ot(self, path: str | os.PathLike[str], *, colour: bool | None = None) -> None:
        """Write the `.ot` file atomically; ColorOcTree when the map keeps colour."""
        write_bytes_atomic(Path(path), self.ot_bytes(colour=colour))
