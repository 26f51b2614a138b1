"""The mapper's inner loops, compiled (numba): a point, a ray or a key at a time, no array per step.

**The ray walk** of OctoMap's `computeRayKeys`. The vectorised walk (mapper/voxelmap.py) advances every ray one voxel per NumPy pass, about ten
array operations a step over all rays still going: at 20,000 rays of 2-4 m that was a third of the
mapper's time per keyframe. Compiled, each ray runs its own loop in registers. The arithmetic is
the same to the bit: the walk only adds float64 `tDelta` to `tMax`, compares, and adds int64
steps, so no operation can be fused or reordered into another result, whatever the CPU; the ray
setup (float32 direction, `tMax`, `tDelta`) stays in NumPy (`voxelmap._dda_start`).

**The image-grid outlier measure** (mapper/cloud.py: image_outlier_removal): each point's squared
distances to the points of its 5x5 pixel window, in float32 as (dx² + dy²) + dz², the nearest
IMAGE_NEAREST of them, their square roots summed in float64 from the smallest up. In NumPy this was
24 full-image passes and a partition along the short axis, half the cost of a keyframe's cloud.
Every operation is a single IEEE rounding in a fixed order (numba fuses no multiply-add without
`fastmath`), so the bytes do not depend on the CPU either.

**Sorted lookups** (mapper/voxelstore.py): where each of a scan's sorted keys is in a slab's sorted
keys. One walk through both, a few steps at a time and galloping over gaps: 2-5× faster than a
binary search per key (`np.searchsorted`), whose every probe is a cache miss in a large table. The
same positions, integers only.

**Inserting and merging sorted keys** (mapper/voxelmap.py, mapper/voxelstore.py): a scan's free
voxels read off its dense grid in the grid's order, which is already the packed keys' order; its
free and occupied keys merged; its new keys inserted into a level's three arrays; each one pass
instead of a sort, two integer divisions per key, or an `np.insert` per array. Integers and copies:
the same arrays.

**Unique keys** (mapper/cloud.py: `_merge_voxels`, the 1 cm grid): `np.unique` with inverse and
counts by a stable radix sort, 11 bits a pass: a few linear passes instead of a comparison sort.

**Sums per voxel** (mapper/cloud.py: `_merge_voxels`, the 1 cm grid): each row added to its
voxel's sum in row order, as `np.bincount` adds its weights, so the same sums; one pass for all
columns instead of one `bincount` per column.

numba (and its llvmlite) is a well-kept compiler of NumPy-style Python, ~45 MB of wheels with no
system libraries; a kernel compiles once per machine (~1 s) and is cached beside this file.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["accumulate_rows", "find_sorted", "insert_sorted", "key_triples", "marked_keys", "merge_sorted",
           "nearest_mean_distances", "unique_keys", "voxel_means", "walk_rays"]


@njit(cache=True, nogil=True)
def _walk(tmax: np.ndarray, tdelta: np.ndarray, lin_step: np.ndarray, length: np.ndarray, lin_start: int,
          lin_end: np.ndarray, grid: np.ndarray, max_iter: int) -> int:
    """Each ray's voxels after its first, up to (not including) its end voxel or its length,
    marked 1 in `grid`; returns the index of a ray that did not end within `max_iter` steps, or -1."""
    for r in range(tmax.shape[0]):
        tx, ty, tz = tmax[r, 0], tmax[r, 1], tmax[r, 2]
        dx, dy, dz = tdelta[r, 0], tdelta[r, 1], tdelta[r, 2]
        lin, end, ray_len = lin_start, lin_end[r], length[r]
        for _ in range(max_iter):
            if tx < ty:
                if tx < tz:
                    tx += dx
                    lin += lin_step[r, 0]
                else:
                    tz += dz
                    lin += lin_step[r, 2]
            elif ty < tz:
                ty += dy
                lin += lin_step[r, 1]
            else:
                tz += dz
                lin += lin_step[r, 2]
            if lin == end or min(min(tx, ty), tz) > ray_len:
                break
            grid[lin] = 1
        else:
            return r
    return -1


def walk_rays(tmax: np.ndarray, tdelta: np.ndarray, lin_step: np.ndarray, length: np.ndarray, lin_start: int,
              lin_end: np.ndarray, grid: np.ndarray, max_iter: int) -> bool:
    """Mark every ray's free voxels in the dense scan grid `grid` (uint8, linear indices); False if
    a ray did not end within `max_iter` steps (inconsistent geometry)."""
    return _walk(np.ascontiguousarray(tmax), np.ascontiguousarray(tdelta), np.ascontiguousarray(lin_step),
                 np.ascontiguousarray(length), int(lin_start), np.ascontiguousarray(lin_end), grid,
                 int(max_iter)) < 0


@njit(cache=True, nogil=True)
def _nearest_means(planes: np.ndarray, valid: np.ndarray, n: int, radius: int, offsets: np.ndarray,
                   nearest: int) -> np.ndarray:
    h, w = valid.shape
    out = np.empty(n, np.float64)
    best = np.empty(nearest, np.float32)
    i = 0
    for y in range(h):
        for x in range(w):
            if not valid[y, x]:
                continue
            py, px = y + radius, x + radius
            cx, cy, cz = planes[0, py, px], planes[1, py, px], planes[2, py, px]
            for m in range(nearest):
                best[m] = np.inf
            for o in range(offsets.shape[0]):
                yy, xx = py + offsets[o, 0], px + offsets[o, 1]
                ex = planes[0, yy, xx] - cx
                ey = planes[1, yy, xx] - cy
                ez = planes[2, yy, xx] - cz
                d = ex * ex + ey * ey
                d = d + ez * ez
                if best[nearest - 1] > d:  # into the ascending list of the `nearest` smallest so far
                    m = nearest - 1
                    while m > 0 and best[m - 1] > d:
                        best[m] = best[m - 1]
                        m -= 1
                    best[m] = d
            total = 0.0
            for m in range(nearest):
                total += np.sqrt(np.float64(best[m]))
            out[i] = total
            i += 1
    return out


def _ring_offsets(radius: int) -> np.ndarray:
    """The window's pixel offsets (dy, dx) without the centre, nearest ring first: on a surface the
    nearest points are mostly there, so the farther rings seldom change the list (fewer mispredicted
    branches); the list, and so the result, is the same in any order."""
    offsets = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1) if dy or dx]
    return np.array(sorted(offsets, key=lambda o: (max(abs(o[0]), abs(o[1])), abs(o[0]) + abs(o[1]), o)), np.int64)


def nearest_mean_distances(points: np.ndarray, valid: np.ndarray, radius: int, nearest: int) -> np.ndarray:
    """Per point (the `valid` pixels of the image grid, row-major): the sum of the square roots of
    its `nearest` smallest squared distances to the points of its window, smallest first (inf when
    the window holds fewer than `nearest` points)."""
    h, w = valid.shape
    # one padded float32 plane per coordinate; a pixel without a point is inf, so is a distance to it
    planes = np.full((3, h + 2 * radius, w + 2 * radius), np.inf, dtype=np.float32)
    for j in range(3):
        planes[j, radius:radius + h, radius:radius + w][valid] = points[:, j]
    return _nearest_means(planes, np.ascontiguousarray(valid), int(points.shape[0]), int(radius),
                          _ring_offsets(int(radius)), int(nearest))


@njit(cache=True, nogil=True)
def _accumulate(inverse: np.ndarray, offset: int, values: np.ndarray, out: np.ndarray) -> None:
    for i in range(values.shape[0]):
        g = inverse[offset + i]
        for j in range(values.shape[1]):
            out[g, j] += values[i, j]


def accumulate_rows(inverse: np.ndarray, offset: int, values: np.ndarray, out: np.ndarray) -> None:
    """`out[inverse[offset + i]] += values[i]` for every row i of `values`, in row order (float64 `out`)."""
    _accumulate(inverse, int(offset), np.ascontiguousarray(values), out)


@njit(cache=True, nogil=True)
def _means(sums: np.ndarray, colour_sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    out = np.empty(colour_sums.shape, np.uint8)
    for g in range(counts.shape[0]):
        n = np.float64(counts[g])
        for j in range(3):
            sums[g, j] = sums[g, j] / n
            c = np.rint(colour_sums[g, j] / n)
            out[g, j] = np.uint8(0.0 if c < 0.0 else (255.0 if c > 255.0 else c))
    return out


def voxel_means(sums: np.ndarray, colour_sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """A voxel merge's last step in one pass: `sums /= counts` in place (the mean point), and the
    mean colours rounded half to even and clipped to 0-255 as uint8 (NumPy's `rint` and `clip`:
    the same bytes). `sums` and `colour_sums` (M,3) float64, `counts` (M,) int64."""
    return _means(sums, np.ascontiguousarray(colour_sums), np.ascontiguousarray(counts, dtype=np.int64))


@njit(cache=True, nogil=True)
def _triples(unique: np.ndarray, span_y: int, span_z: int, lo: np.ndarray) -> np.ndarray:
    out = np.empty((unique.shape[0], 3), np.int64)
    yz = span_y * span_z
    for g in range(unique.shape[0]):
        k = unique[g]
        x = k // yz
        r = k - x * yz
        y = r // span_z
        out[g, 0] = x + lo[0]
        out[g, 1] = y + lo[1]
        out[g, 2] = r - y * span_z + lo[2]
    return out


def key_triples(unique: np.ndarray, span: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """The (M,3) int64 voxel triples of non-negative linear keys `(x * span_y + y) * span_z + z`, plus `lo`."""
    return _triples(np.ascontiguousarray(unique, dtype=np.int64), int(span[1]), int(span[2]),
                    np.ascontiguousarray(lo, dtype=np.int64))


@njit(cache=True, nogil=True)
def _find_sorted(keys: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = keys.shape[0]
    pos = np.empty(wanted.shape[0], np.int64)
    found = np.zeros(wanted.shape[0], np.bool_)
    j = 0
    for i in range(wanted.shape[0]):
        w = wanted[i]
        k = 0
        while k < 8 and j < n and keys[j] < w:  # a few steps: the next key is usually close
            j += 1
            k += 1
        if k == 8 and j < n and keys[j] < w:  # a gap: gallop, then a binary search
            lo, step = j, 8
            hi = j + step
            while hi < n and keys[hi] < w:
                lo = hi
                step *= 2
                hi = lo + step
            a, b = lo + 1, min(hi, n)
            while a < b:
                mid = (a + b) >> 1
                if keys[mid] < w:
                    a = mid + 1
                else:
                    b = mid
            j = a
        pos[i] = j
        found[i] = j < n and keys[j] == w
    return pos, found


def find_sorted(keys: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ascending `wanted` in ascending `keys` (int64): where each is or would go
    (`np.searchsorted(keys, wanted)`), and whether it is there."""
    return _find_sorted(np.ascontiguousarray(keys, dtype=np.int64), np.ascontiguousarray(wanted, dtype=np.int64))


@njit(cache=True, nogil=True)
def _marked(grid: np.ndarray, count: int, ny: int, nz: int, lo0: int, lo1: int, lo2: int) -> np.ndarray:
    out = np.empty(count, np.int64)
    nx = grid.shape[0] // (ny * nz)
    lin, j = 0, 0
    for x in range(nx):
        for y in range(ny):
            row = ((x + lo0) << 32) | ((y + lo1) << 16)
            for z in range(nz):
                if grid[lin]:
                    out[j] = row | (z + lo2)
                    j += 1
                lin += 1
    return out


def marked_keys(grid: np.ndarray, shape: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """The packed OctoMap keys (x << 32 | y << 16 | z) of the marked cells of a dense scan grid
    (uint8, x-major over the key box from `lo` of `shape`), ascending: one walk, in the grid's own
    order, instead of their linear indices and two integer divisions each."""
    return _marked(grid, int(np.count_nonzero(grid)), int(shape[1]), int(shape[2]), int(lo[0]), int(lo[1]),
                   int(lo[2]))


@njit(cache=True, nogil=True)
def _merge(a: np.ndarray, va: np.ndarray, b: np.ndarray, vb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n, m = a.shape[0], b.shape[0]
    keys = np.empty(n + m, np.int64)
    vals = np.empty(n + m, va.dtype)
    i = j = k = 0
    while i < n and j < m:
        if b[j] < a[i]:
            keys[k], vals[k] = b[j], vb[j]
            j += 1
        else:
            keys[k], vals[k] = a[i], va[i]
            i += 1
        k += 1
    while i < n:
        keys[k], vals[k] = a[i], va[i]
        i += 1
        k += 1
    while j < m:
        keys[k], vals[k] = b[j], vb[j]
        j += 1
        k += 1
    return keys, vals


def merge_sorted(a: np.ndarray, va: np.ndarray, b: np.ndarray, vb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two ascending int64 key arrays with their values, merged into one ascending pair: what a
    stable argsort of their concatenation gives (`a`'s first on equal keys), in one pass."""
    return _merge(np.ascontiguousarray(a, dtype=np.int64), np.ascontiguousarray(va),
                  np.ascontiguousarray(b, dtype=np.int64), np.ascontiguousarray(vb, dtype=va.dtype))


@njit(cache=True, nogil=True)
def _insert(keys: np.ndarray, logodds: np.ndarray, colours: np.ndarray, at: np.ndarray, new_keys: np.ndarray,
            new_logodds: np.ndarray, new_colour: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n, m = keys.shape[0], new_keys.shape[0]
    ok = np.empty(n + m, np.int64)
    ol = np.empty(n + m, np.float32)
    oc = np.empty((n + m, 3), np.uint8)
    i = k = 0
    for j in range(m + 1):
        stop = at[j] if j < m else n
        while i < stop:
            ok[k], ol[k] = keys[i], logodds[i]
            oc[k, 0], oc[k, 1], oc[k, 2] = colours[i, 0], colours[i, 1], colours[i, 2]
            i += 1
            k += 1
        if j < m:
            ok[k], ol[k] = new_keys[j], new_logodds[j]
            oc[k, 0], oc[k, 1], oc[k, 2] = new_colour[0], new_colour[1], new_colour[2]
            k += 1
    return ok, ol, oc


def insert_sorted(keys: np.ndarray, logodds: np.ndarray, colours: np.ndarray, at: np.ndarray, new_keys: np.ndarray,
                  new_logodds: np.ndarray, new_colour: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`np.insert` of `new_keys`, `new_logodds` and one colour (a value or 3) for all of them before
    positions `at` (non-decreasing) of the three arrays of a level, in one pass."""
    return _insert(keys, logodds, np.ascontiguousarray(colours), np.ascontiguousarray(at, dtype=np.int64),
                   np.ascontiguousarray(new_keys, dtype=np.int64), np.ascontiguousarray(new_logodds, dtype=np.float32),
                   np.broadcast_to(np.asarray(new_colour, dtype=np.uint8), (3,)).copy())


RADIX_BITS = 11  # unique_keys: a pass sorts this many bits of the keys (2048 buckets: in L1)


@njit(cache=True, nogil=True)
def _unique_keys(keys: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = keys.shape[0]
    k, idx = keys.copy(), np.arange(n)
    k2, idx2 = np.empty(n, np.int64), np.empty(n, np.int64)
    size = 1 << RADIX_BITS
    mask = size - 1
    count = np.empty(size, np.int64)
    shift = 0
    while shift < bits:  # least significant digit first, each pass stable: a stable sort of the keys
        count[:] = 0
        for i in range(n):
            count[(k[i] >> shift) & mask] += 1
        at = 0
        for d in range(size):
            c = count[d]
            count[d] = at
            at += c
        for i in range(n):
            d = (k[i] >> shift) & mask
            k2[count[d]], idx2[count[d]] = k[i], idx[i]
            count[d] += 1
        k, k2, idx, idx2 = k2, k, idx2, idx
        shift += RADIX_BITS
    groups = 0
    for i in range(n):
        if i == 0 or k[i] != k[i - 1]:
            groups += 1
    unique = np.empty(groups, np.int64)
    counts = np.zeros(groups, np.int64)
    inverse = np.empty(n, np.int64)
    g = -1
    for i in range(n):
        if i == 0 or k[i] != k[i - 1]:
            g += 1
            unique[g] = k[i]
        counts[g] += 1
        inverse[idx[i]] = g
    return unique, inverse, counts


def unique_keys(keys: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`np.unique(keys, return_inverse=True, return_counts=True)` of non-negative int64 keys below
    2**bits, by a stable radix sort: integers only, the same arrays, in a few linear passes."""
    return _unique_keys(np.ascontiguousarray(keys, dtype=np.int64), int(bits))
