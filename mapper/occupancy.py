"""The occupancy backends' common interface and the factory that picks one by name.

It lives apart from both backends so that neither imports the other: `voxelmap` (our NumPy map)
and `octree` (OctoMap through pyoctomap) share only `sensor_model` and `octokeys`.
"""

from __future__ import annotations

import os
from typing import Protocol

import numpy as np

from octolog.kit.errors import MapError
from octolog.mapper.octree import OccupancyOctree
from octolog.mapper.params import BACKENDS
from octolog.mapper.sensor_model import SensorModel
from octolog.mapper.voxelmap import Region, VoxelOccupancyMap

__all__ = ["BACKENDS", "OccupancyMap", "make_occupancy_map"]


class OccupancyMap(Protocol):
    """What the mapper, the grid projection and the publisher need from an occupancy backend."""

    backend: str
    resolution: float
    colour: bool
    model: SensorModel

    def insert(self, points_world: np.ndarray, origin: np.ndarray, *, colours: np.ndarray | None = None,
               max_range_m: float = -1.0) -> int: ...

    def clear(self) -> None: ...

    def bt_bytes(self) -> bytes: ...

    def ot_bytes(self, *, colour: bool | None = None) -> bytes: ...

    def write_bt(self, path: str | os.PathLike[str]) -> None: ...

    def write_ot(self, path: str | os.PathLike[str], *, colour: bool | None = None) -> None: ...

    def occupied_centres(self, max_voxels: int | None = None) -> np.ndarray: ...

    def free_centres(self, max_voxels: int | None = None) -> np.ndarray: ...

    def classify(self, points: np.ndarray) -> np.ndarray: ...

    def stats(self) -> dict: ...


def make_occupancy_map(backend: str = "numpy", resolution: float = 0.05, *, colour: bool = True,
                       model: SensorModel = SensorModel(), region: Region | None = None,
                       confirm_within: int = 0) -> OccupancyMap:
    """An occupancy map with the common interface (`OccupancyMap`).

    backend "numpy": `VoxelOccupancyMap` (own, vectorised); "octomap": `OccupancyOctree`
    (pyoctomap, the reference), with a `ColorOcTree` mirror for colour when `colour` is true.
    `region` (a shard's tiles) keeps only its voxels, `confirm_within` counts an end point once
    confirmed (keeps people walking by out):
    the numpy backend only.
    """
    if backend == "numpy":
        return VoxelOccupancyMap(resolution, model=model, colour=colour, region=region, confirm_within=confirm_within)
    if region is not None:
        raise MapError("a map shard (mapper.shard) needs mapper.backend = \"numpy\"")
    if backend == "octomap":
        return OccupancyOctree(resolution, model=model, colour=colour)
    raise MapError(f"unknown occupancy map backend {backend!r} (want 'numpy' or 'octomap')")
