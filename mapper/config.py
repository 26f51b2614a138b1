"""Mapper settings."""

from __future__ import annotations

from dataclasses import dataclass

from octolog.errors import ConfigError


@dataclass(frozen=True)
class MapperConfig:
    resolution_m: float = 0.05  # occupancy octree leaf size
    voxel_m: float = 0.01  # dense cloud voxel filter (second layer)
    max_range_m: float = 4.0  # depth readings beyond this are ignored
    pixel_stride: int = 2  # back-project every n-th pixel in each direction
    sor_neighbors: int = 20  # statistical outlier removal (first layer)
    sor_std_ratio: float = 2.0
    # false: 1 cm voxel grid before the outlier filter (3x faster, same result on real data);
    # true: the paper's order, outlier filter on the raw back-projected points first
    sor_first: bool = False
    wait_for: tuple[str, ...] = ()
    wait_timeout_s: float = 60.0

    def validate(self) -> None:
        for key in ("resolution_m", "voxel_m", "max_range_m"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"mapper.{key} {getattr(self, key)}: want > 0")
        if self.pixel_stride < 1:
            raise ConfigError(f"mapper.pixel_stride {self.pixel_stride}: want >= 1")
