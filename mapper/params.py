"""The mapper core's parameters: one frozen object, grouped by the part of the core that uses them.

`MapperConfig.params()` builds it from the validated config (the one place values are checked);
`Mapper` takes it whole, as KISS-ICP hands its config to its pipeline. No defaults here: the
defaults live in `MapperConfig` (and OctoMap's in `SensorModel`), so there is one source of them.
"""

from __future__ import annotations

from dataclasses import dataclass

from octolog.mapper.sensor_model import SensorModel
from octolog.mapper.tiles import Tiles

__all__ = ["BACKENDS", "CloudParams", "GridParams", "MapperParams", "OccupancyParams"]

BACKENDS = ("numpy", "octomap")  # occupancy map backends (mapper.occupancy.make_occupancy_map)


@dataclass(frozen=True)
class CloudParams:
    """A keyframe's dense cloud: back-projection and the two filter layers (mapper.cloud)."""

    max_range_m: float  # depth readings beyond this are dropped (and never reach the octree)
    pixel_stride: int  # back-project every n-th pixel in each direction
    voxel_m: float  # voxel grid of the second filter layer, per keyframe and across keyframes
    sor_neighbors: int  # statistical outlier removal: k nearest neighbours
    sor_std_ratio: float  # ... and the threshold in standard deviations above the mean distance
    sor_first: bool  # the outlier filter before the voxel grid (the paper's order) instead of after
    outliers: str  # the first layer on the image grid ("image") or over 3D k nearest ("knn")
    full_per_s: float  # keyframes a second at pixel_stride; more in that second: burst_stride (0: no limit)
    burst_stride: int


@dataclass(frozen=True)
class OccupancyParams:
    """The occupancy map: which backend, its voxel size, colour, and OctoMap's sensor model."""

    backend: str  # one of BACKENDS
    resolution_m: float
    colour: bool
    sensor: SensorModel
    confirm_within: int  # end points count once confirmed by a scan this recent (mapper.voxelmap; 0: off)


DEFAULT_UP = (0.0, -1.0, 0.0)  # a level optical-frame camera: image "up" is -y


@dataclass(frozen=True)
class GridParams:
    """The 2D grid: a height band in a level frame whose +z is `up` (mapper.grid)."""

    up: tuple[float, ...]
    camera_height_m: float
    z_min_m: float
    z_max_m: float
    resolution_m: float


@dataclass(frozen=True)
class MapperParams:
    """Everything `Mapper` needs, and nothing of the process around it (bus, publishing, robots)."""

    cloud: CloudParams
    occupancy: OccupancyParams
    grid: GridParams
    max_extent_m: float  # cameras farther than this from the origin are refused
    tiles: Tiles | None  # a shard of the map: only these tiles' voxels (mapper.tiles)
    move_tolerance_m: float  # a keyframe moved less at every point keeps its voxels in a snapshot (0: exact)
