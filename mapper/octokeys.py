"""OctoMap's key arithmetic in NumPy, and the per-scan voxel colour rule both backends share.

Keys follow OctoMap 1.10 for a 16-level tree (`coordToKey`, `keyToCoord`, `Vector3::norm`) to the
last bit, so that voxels computed here are the voxels OctoMap itself would address.
"""

from __future__ import annotations

import numpy as np

__all__ = ["TREE_DEPTH", "TREE_MAX_VAL", "key_to_coord", "norm32", "pack", "scan_voxel_colours", "to_key", "unpack"]

TREE_DEPTH = 16
TREE_MAX_VAL = 32768  # key offset of a 16-level OctoMap tree


def to_key(c32: np.ndarray, res_factor: float) -> np.ndarray:
    """OctoMap `coordToKey` of float32 coordinates (computed in double), as int64."""
    x = c32.astype(np.float64)
    x *= res_factor
    np.floor(x, out=x)
    k = x.astype(np.int64)
    k += TREE_MAX_VAL
    return k


def key_to_coord(key: np.ndarray, res: float) -> np.ndarray:
    """OctoMap `keyToCoord` (double): ((key - 32768) + 0.5) * res."""
    return ((np.asarray(key, dtype=np.int64) - TREE_MAX_VAL).astype(np.float64) + 0.5) * res


def norm32(d: np.ndarray) -> np.ndarray:
    """octomath `Vector3::norm()`: float32 sum of squares, sqrt in double."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.sqrt(((x * x + y * y) + z * z).astype(np.float64))


def pack(keys: np.ndarray) -> np.ndarray:
    """(N,3) keys in [0, 65536) -> int64 (x << 32 | y << 16 | z), ordered like (x, y, z)."""
    k = keys.astype(np.int64)
    return (k[:, 0] << 32) | (k[:, 1] << 16) | k[:, 2]


def unpack(packed: np.ndarray) -> np.ndarray:
    """Inverse of `pack`: int64 packed keys -> (N,3) int64 keys."""
    p = packed.astype(np.int64)
    return np.stack([(p >> 32) & 0xFFFF, (p >> 16) & 0xFFFF, p & 0xFFFF], axis=1)


def scan_voxel_colours(points_world: np.ndarray, colours: np.ndarray, origin: np.ndarray,
                       resolution: float, max_range_m: float = -1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per occupied end-point voxel of one scan: (centre (M,3) float64, mean colour (M,3) uint8).

    The same rule `VoxelOccupancyMap` applies (voxels whose centre is within `max_range_m` of the
    origin; mean rounded half to even), for feeding `ColorOcTree.averageNodeColor` in the
    OctoMap backend.
    """
    p32 = np.asarray(points_world, dtype=np.float64).astype(np.float32)
    o32 = np.asarray(origin, dtype=np.float64).reshape(3).astype(np.float32)
    keys = to_key(p32, 1.0 / resolution)
    ukeys, inverse = np.unique(pack(keys), return_inverse=True)
    ukeys = unpack(ukeys)
    centres32 = key_to_coord(ukeys, resolution).astype(np.float32)
    ok = np.ones(ukeys.shape[0], bool) if max_range_m < 0 else norm32(centres32 - o32) <= max_range_m
    m = ukeys.shape[0]
    cnt = np.bincount(inverse, minlength=m)
    mean = np.stack([np.bincount(inverse, weights=colours[:, j].astype(np.float64), minlength=m)
                     for j in range(3)], axis=1)
    mean = np.clip(np.rint(mean / np.maximum(cnt, 1)[:, None]), 0, 255).astype(np.uint8)
    return key_to_coord(ukeys[ok], resolution), mean[ok]
