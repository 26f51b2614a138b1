"""Probabilistic occupancy octree (OctoMap, via pyoctomap) with ray-cast free space.

Wraps `pyoctomap.OcTree` with OctoMap's sensor model set explicitly (a `SensorModel`; by default
hit 0.7, miss 0.4, clamping 0.12/0.97). Quirks of the binding handled here:

- OctoMap's `writeBinary` converts the tree to maximum likelihood and prunes it *in place*, which
  destroys the log-odds needed for later inserts. `bt_bytes()` therefore serialises the full tree
  (`.ot`, lossless log-odds), reads it into a throw-away copy and calls `writeBinary` on the copy.
- `insertPointCloud` wants float64 arrays and casts to float32 inside; `discretize=True` keeps one
  end point per voxel (in Python) and ray-casts to voxel centres (in C++), like OctoMap's
  `insertPointCloud(..., discretize=true)`.
- The library is built without OpenMP, so ray casting is serial and updates are deterministic.
- With `colour=True` a `pyoctomap.ColorOcTree` mirror receives the same scans (same occupancy
  arithmetic) plus `averageNodeColor` per occupied end-point voxel with the scan's mean colour; it
  only serves `.ot` output. OctoMap prunes in memory as it inserts (8 siblings with equal log-odds
  collapse), and a ColorOcTree prunes on log-odds alone, averaging the children's colours, so its
  colours are lossy where that happens; `VoxelOccupancyMap` keeps every voxel's colour.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pyoctomap

from octolog.kit.errors import MapError
from octolog.kit.files import write_bytes_atomic
from octolog.mapper.octokeys import TREE_MAX_VAL, scan_voxel_colours
from octolog.mapper.sensor_model import SensorModel

__all__ = ["OccupancyOctree"]


class OccupancyOctree:
    """An OctoMap OcTree at `resolution` metres with an explicit, fixed sensor model (`model`)."""

    backend = "octomap"

    def __init__(self, resolution: float = 0.05, *, model: SensorModel = SensorModel(), colour: bool = False) -> None:
        model.check(resolution)
        self.resolution = float(resolution)
        self.model = model
        self.colour = bool(colour)
        self._tree = self._new_tree()
        self._ctree = self._new_colour_tree() if self.colour else None
        self._leaf_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _new_colour_tree(self) -> pyoctomap.ColorOcTree:
        tree = pyoctomap.ColorOcTree(self.resolution)
        self._apply_model(tree)
        return tree

    def _new_tree(self) -> pyoctomap.OcTree:
        tree = pyoctomap.OcTree(self.resolution)
        self._apply_model(tree)
        return tree

    def _apply_model(self, tree: pyoctomap.OcTree) -> None:
        m = self.model
        tree.setProbHit(float(m.prob_hit))
        tree.setProbMiss(float(m.prob_miss))
        tree.setClampingThresMin(float(m.clamp_min))
        tree.setClampingThresMax(float(m.clamp_max))
        tree.setOccupancyThres(float(m.occupancy_thres))

    @property
    def tree(self) -> pyoctomap.OcTree:
        """The underlying pyoctomap tree, for read-only queries (mutating it bypasses the leaf cache)."""
        return self._tree

    def insert(
        self,
        points_world: np.ndarray,
        origin: np.ndarray,
        *,
        colours: np.ndarray | None = None,
        max_range_m: float = -1.0,
    ) -> int:
        """Integrate one scan: end points occupied, voxels along each ray from `origin` free.

        `max_range_m` < 0 means unlimited; longer rays are cut there and only mark free space.
        Pixels without a depth reading never reach here, so they clear no space.
        `colours` (N,3) uint8 go to the ColorOcTree mirror (ignored without `colour=True`).
        Returns the number of points handed to OctoMap (before its per-voxel discretisation).
        """
        pts = np.asarray(points_world)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MapError(f"octree points must have shape (N, 3), got {pts.shape}")
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        org = np.ascontiguousarray(np.asarray(origin, dtype=np.float64).reshape(-1))
        if org.shape != (3,):
            raise MapError(f"sensor origin must have 3 coordinates, got shape {np.shape(origin)}")
        if not np.isfinite(org).all():
            raise MapError("sensor origin contains NaN or infinite values")
        if not np.isfinite(pts).all():
            raise MapError("octree points contain NaN or infinite coordinates")
        if not np.isfinite(max_range_m) or max_range_m == 0:
            raise MapError(f"max_range_m must be > 0 (or negative for unlimited), got {max_range_m}")
        if colours is not None and (np.shape(colours) != pts.shape or np.asarray(colours).dtype != np.uint8):
            raise MapError(f"colours must be ({pts.shape[0]}, 3) uint8, got {np.shape(colours)}")
        limit = TREE_MAX_VAL * self.resolution
        if pts.shape[0] and (np.abs(pts).max() >= limit or np.abs(org).max() >= limit):
            raise MapError(f"points outside the octree's addressable cube of +/-{limit:g} m")
        if pts.shape[0] == 0:
            return 0
        n = self._tree.insertPointCloud(
            pts, org, max_range=float(max_range_m) if max_range_m > 0 else -1.0,
            lazy_eval=False, discretize=True,
        )
        if self._ctree is not None:
            self._insert_colour(pts, org, colours, max_range_m)
        self._leaf_cache = None
        return int(n)

    def _insert_colour(self, pts: np.ndarray, org: np.ndarray, colours: np.ndarray | None,
                       max_range_m: float) -> None:
        """Same scan into the ColorOcTree mirror, then averageNodeColor per occupied end voxel."""
        ctree = self._ctree
        ctree.insertPointCloud(pts, org, max_range=float(max_range_m) if max_range_m > 0 else -1.0,
                               lazy_eval=False, discretize=True)
        if colours is None:
            return
        centres, rgb = scan_voxel_colours(pts, colours, org, self.resolution, max_range_m)
        for c, (r, g, b) in zip(centres, rgb.tolist()):
            ctree.averageNodeColor(c, r, g, b)
        ctree.updateInnerOccupancy()  # inner colours = average of the children

    def clear(self) -> None:
        """Forget everything (e.g. before re-integrating keyframes after a loop closure)."""
        self._tree = self._new_tree()
        self._ctree = self._new_colour_tree() if self.colour else None
        self._leaf_cache = None

    # ---- serialisation -------------------------------------------------------------------------

    def ot_bytes(self, *, colour: bool | None = None) -> bytes:
        """The full probabilistic tree as `.ot`: ColorOcTree if `colour` (default: the map's flag), else OcTree."""
        colour = self.colour if colour is None else bool(colour)
        if colour and self._ctree is None:
            raise MapError("this octree keeps no colour (create it with colour=True)")
        data = (self._ctree if colour else self._tree).write()
        if not isinstance(data, bytes):
            raise MapError("OctoMap failed to serialise the octree")
        return data

    def bt_bytes(self) -> bytes:
        """OctoMap binary `.bt` (max-likelihood, pruned) without touching the in-memory log-odds."""
        with tempfile.TemporaryDirectory(prefix="octolog-bt-") as tmp:
            ot_path = os.path.join(tmp, "copy.ot")
            with open(ot_path, "wb") as f:
                f.write(self.ot_bytes(colour=False))
            copy = self._tree.read(ot_path)
        if copy is None:
            raise MapError("OctoMap failed to copy the octree for binary output")
        self._apply_model(copy)  # toMaxLikelihood uses the clamping thresholds
        data = copy.writeBinary()  # toMaxLikelihood + prune on the copy, then serialise
        if not isinstance(data, bytes):
            raise MapError("OctoMap failed to serialise the octree as .bt")
        return data

    def write_bt(self, path: str | os.PathLike[str]) -> None:
        """Write the `.bt` file atomically (temporary file then rename)."""
        write_bytes_atomic(Path(path), self.bt_bytes())

    def write_ot(self, path: str | os.PathLike[str], *, colour: bool | None = None) -> None:
        """Write the `.ot` file atomically; ColorOcTree when the octree keeps colour."""
        write_bytes_atomic(Path(path), self.ot_bytes(colour=colour))

    # ---- queries -------------------------------------------------------------------------------

    def _leaves(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All known leaves as (first voxel index (N,3) int64, width in voxels (N,), occupied (N,))."""
        if self._leaf_cache is None:
            tree = self._tree
            coords: list[list[float]] = []
            sizes: list[float] = []
            occ: list[bool] = []
            for it in tree.begin_leafs():
                coords.append(it.getCoordinate())
                sizes.append(it.getSize())
                occ.append(tree.isNodeOccupied(it))
            res = self.resolution
            if coords:
                c = np.asarray(coords, dtype=np.float64)
                width = np.rint(np.asarray(sizes, dtype=np.float64) / res).astype(np.int64)
                first = np.rint(c / res - width[:, None] / 2.0).astype(np.int64)
                occupied = np.asarray(occ, dtype=bool)
            else:
                first = np.zeros((0, 3), dtype=np.int64)
                width = np.zeros(0, dtype=np.int64)
                occupied = np.zeros(0, dtype=bool)
            order = np.lexsort((first[:, 2], first[:, 1], first[:, 0]))
            self._leaf_cache = (first[order], width[order], occupied[order])
        return self._leaf_cache

    def _centres(self, want_occupied: bool, max_voxels: int | None) -> np.ndarray:
        first, width, occupied = self._leaves()
        sel = occupied == want_occupied
        first, width = first[sel], width[sel]
        total = int((width.astype(np.int64) ** 3).sum())
        if max_voxels is not None and total > max_voxels:
            raise MapError(f"{total} voxels exceed max_voxels={max_voxels}")
        if total == 0:
            return np.zeros((0, 3), dtype=np.float64)
        parts = [first[width == 1]]
        for w in np.unique(width[width > 1]):
            g = np.arange(w)
            off = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
            parts.append((first[width == w][:, None, :] + off[None, :, :]).reshape(-1, 3))
        idx = np.concatenate(parts)
        idx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
        # Same arithmetic as OctoMap's keyToCoord: ((key - 32768) + 0.5) * resolution.
        return (idx.astype(np.float64) + 0.5) * self.resolution

    def occupied_centres(self, max_voxels: int | None = None) -> np.ndarray:
        """Centres (N,3) of occupied voxels at full resolution, sorted by (x, y, z) index."""
        return self._centres(True, max_voxels)

    def free_centres(self, max_voxels: int | None = None) -> np.ndarray:
        """Centres (N,3) of free voxels at full resolution, sorted; pruned free leaves are expanded."""
        return self._centres(False, max_voxels)

    def classify(self, points: np.ndarray) -> np.ndarray:
        """Per point: 1 occupied, 0 free, -1 unknown (int8)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MapError(f"query points must have shape (N, 3), got {pts.shape}")
        out = np.full(pts.shape[0], -1, dtype=np.int8)
        for i, p in enumerate(pts):
            node = self._tree.search(np.ascontiguousarray(p))
            if node is not None:
                out[i] = 1 if self._tree.isNodeOccupied(node) else 0
        return out

    def stats(self) -> dict:
        """Counts and volumes: leaves, voxels at full resolution, known volume, memory."""
        first, width, occupied = self._leaves()
        vox = width.astype(np.int64) ** 3
        v1 = self.resolution**3
        occ_vox = int(vox[occupied].sum())
        free_vox = int(vox[~occupied].sum())
        return {
            "resolution_m": self.resolution,
            "occupied_leaves": int(occupied.sum()),
            "free_leaves": int((~occupied).sum()),
            "occupied_voxels": occ_vox,
            "free_voxels": free_vox,
            "occupied_volume_m3": occ_vox * v1,
            "free_volume_m3": free_vox * v1,
            "known_volume_m3": (occ_vox + free_vox) * v1,
            "num_nodes": int(self._tree.size()),
            "memory_bytes": int(self._tree.memoryUsage()),
        }

