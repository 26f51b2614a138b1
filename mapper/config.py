"""Mapper settings."""

from __future__ import annotations

from dataclasses import dataclass

from octolog.errors import ConfigError


@dataclass(frozen=True)
class MapperConfig:
    resolution_m: float = 0.05  # occupancy octree leaf size
    # "numpy": our vectorised occupancy map (same states and files as OctoMap, 1.4-3x faster);
    # "octomap": OctoMap itself through pyoctomap, the reference
    backend: str = "numpy"
    colour: bool = True  # colour per occupied voxel (map.ot is a ColorOcTree)
    voxel_m: float = 0.01  # dense cloud voxel filter (second layer)
    max_range_m: float = 4.0  # depth readings beyond this are ignored
    pixel_stride: int = 2  # back-project every n-th pixel in each direction
    sor_neighbors: int = 20  # statistical outlier removal (first layer)
    sor_std_ratio: float = 2.0
    # false: 1 cm voxel grid before the outlier filter (3x faster, same result on real data);
    # true: the paper's order, outlier filter on the raw back-projected points first
    sor_first: bool = False
    # publish the map (octomap, occupied voxels, 2D grid) every n keyframes and at the end; 0: end only.
    # Counted in keyframes, not seconds, so the session log stays deterministic.
    publish_every: int = 10
    # cameras farther than this from the origin are refused (OctoMap's 5 cm key range is ±1638 m)
    max_extent_m: float = 1000.0
    wait_for: tuple[str, ...] = ()
    wait_timeout_s: float = 60.0

    def validate(self) -> None:
        for key in ("resolution_m", "voxel_m", "max_range_m"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"mapper.{key} {getattr(self, key)}: want > 0")
        if self.backend not in ("numpy", "octomap"):
            raise ConfigError(f"mapper.backend {self.backend!r}: want numpy or octomap")
        if self.publish_every < 0:
            raise ConfigError(f"mapper.publish_every {self.publish_every}: want >= 0")
        if self.pixel_stride < 1:
            raise ConfigError(f"mapper.pixel_stride {self.pixel_stride}: want >= 1")


def make_mapper(cfg: MapperConfig):  # -> mapper.core.Mapper
    from mapper.core import Mapper

    return Mapper(resolution_m=cfg.resolution_m, voxel_m=cfg.voxel_m, max_range_m=cfg.max_range_m,
                  pixel_stride=cfg.pixel_stride, sor_neighbors=cfg.sor_neighbors, sor_std_ratio=cfg.sor_std_ratio,
                  sor_first=cfg.sor_first, max_extent_m=cfg.max_extent_m, backend=cfg.backend, colour=cfg.colour)
