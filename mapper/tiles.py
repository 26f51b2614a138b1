"""The map cut into tiles, each owned by one mapper shard (`mapper.shard = "K/N"`, `mapper.tile_m`).

Tiles are squares of `tile_m` on the map frame's floor (x, y; the map frame is z up), aligned to
multiples of `tile_m` from the origin, each a whole column of heights. Tile (i, j) belongs to
shard `(i + j) mod N + 1`: a checkerboard for two shards, diagonal stripes for more, so every
shard's tiles are spread over the building and a keyframe that sees a few tiles seldom sees them
all. A shard integrates every keyframe whose rays reach one of its tiles, as a single mapper
would, and keeps the updates of the voxels in its tiles only. An occupancy voxel's value depends
only on the rays through it and the order of the keyframes, and a dense-cloud voxel's point only on
the keyframes' points inside it, so the shards' maps are the whole map cut along tile borders,
voxel for voxel: `octolog stitch` (shell/stitch.py) joins them into the same bytes.

Which tile a voxel is in is decided on integer voxel indices, never on coordinates, so an
occupancy voxel (`resolution_m`) and a cloud voxel (`voxel_m`) each fall in exactly one tile: the
tile edge must be a whole number of both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from octolog.kit.errors import ConfigError
from octolog.mapper.octokeys import TREE_MAX_VAL

__all__ = ["Tiles", "parse_shard"]


def parse_shard(text: str) -> tuple[int, int]:
    """"K/N" -> (K, N), 1 <= K <= N; raises ConfigError naming the problem."""
    try:
        k, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise ConfigError(f"mapper.shard {text!r}: want K/N, e.g. 1/2 (shard K of N)") from None
    if not 1 <= k <= n:
        raise ConfigError(f"mapper.shard {text!r}: want 1 <= K <= N")
    return k, n


def _cells(edge_m: float, voxel_m: float, what: str) -> int:
    n = round(edge_m / voxel_m)
    if n < 1 or abs(n * voxel_m - edge_m) > 1e-9 * max(1.0, edge_m):
        raise ConfigError(f"mapper.tile_m {edge_m:g}: want a whole number of {what} ({voxel_m:g} m)")
    return n


@dataclass(frozen=True)
class Tiles:
    """Shard `index` of `count`: which occupancy keys and cloud points are its own."""

    index: int  # 1-based
    count: int
    tile_m: float
    resolution_m: float  # occupancy voxel
    voxel_m: float  # dense-cloud voxel

    def __post_init__(self) -> None:
        _cells(self.tile_m, self.resolution_m, "mapper.resolution_m")
        _cells(self.tile_m, self.voxel_m, "mapper.voxel_m")

    @property
    def name(self) -> str:
        return f"{self.index}/{self.count}"

    def owns(self, ti: np.ndarray, tj: np.ndarray) -> np.ndarray:
        """Per tile (i, j): this shard's?"""
        return (ti + tj) % self.count == self.index - 1

    def _tiles_of_keys(self, kx: np.ndarray, ky: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = _cells(self.tile_m, self.resolution_m, "")
        return (kx - TREE_MAX_VAL) // n, (ky - TREE_MAX_VAL) // n

    def keep_packed(self, packed: np.ndarray) -> np.ndarray:
        """Per packed octree key (mapper.octokeys.pack): in this shard's tiles?"""
        p = packed.astype(np.int64)
        return self.owns(*self._tiles_of_keys((p >> 32) & 0xFFFF, (p >> 16) & 0xFFFF))

    def touches_keys(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Does the box of octree keys [lo, hi] (inclusive, x y z) reach one of this shard's tiles?"""
        return self._owns_any(self._tiles_of_keys(int(lo[0]), int(lo[1])), self._tiles_of_keys(int(hi[0]), int(hi[1])))

    def touches_box(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Does the floor box [lo, hi] (map frame x, y, metres) reach one of this shard's tiles?"""
        first = tuple(int(v) for v in np.floor(np.asarray(lo, float) / self.tile_m))
        last = tuple(int(v) for v in np.floor(np.asarray(hi, float) / self.tile_m))
        return self._owns_any(first, last)

    def _owns_any(self, first: tuple, last: tuple) -> bool:
        """Is one of the tiles from `first` to `last` (i, j, inclusive) this shard's?"""
        ti, tj = np.meshgrid(np.arange(first[0], last[0] + 1), np.arange(first[1], last[1] + 1), indexing="ij")
        return bool(self.owns(ti, tj).any())

    def keep_points(self, points_map: np.ndarray) -> np.ndarray:
        """Per dense-cloud point (map frame): is its cloud voxel in this shard's tiles?"""
        n = _cells(self.tile_m, self.voxel_m, "")
        k = np.floor(points_map[:, :2] / self.voxel_m).astype(np.int64)
        return self.owns(k[:, 0] // n, k[:, 1] // n)

    def describe(self) -> dict:
        """For shard.json: what a stitch checks the shards agree on."""
        return {"shard": self.name, "index": self.index, "count": self.count, "tile_m": self.tile_m,
                "rule": "tile (i, j) = floor(x / tile_m), floor(y / tile_m) in the map frame; shard (i + j) mod N + 1"}
