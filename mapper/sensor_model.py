"""OctoMap's sensor model in one place: hit/miss probabilities, clamping, occupancy threshold.

Both occupancy backends take a `SensorModel`: `VoxelOccupancyMap` does OctoMap's float32 log-odds
arithmetic with it, `OccupancyOctree` hands the probabilities to pyoctomap. The validation lives
here too, so the backends and the mapper config refuse the same models for the same reasons.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from octolog.kit.errors import MapError

__all__ = ["PROBABILITIES", "LogOdds", "SensorModel", "logodds"]

# the model's probability fields, in the order they are checked
PROBABILITIES = ("prob_hit", "prob_miss", "clamp_min", "clamp_max", "occupancy_thres")


def logodds(p: float) -> np.float32:
    """OctoMap's `logodds()`: float(log(p / (1 - p)))."""
    return np.float32(np.log(p / (1.0 - p)))


@dataclass(frozen=True)
class LogOdds:
    """A sensor model as OctoMap stores it: float32 log-odds of each probability."""

    hit: np.float32
    miss: np.float32
    clamp_min: np.float32
    clamp_max: np.float32
    occupancy_thres: np.float32


@dataclass(frozen=True)
class SensorModel:
    """OctoMap's sensor model; the defaults are OctoMap's own (OccupancyOcTreeBase)."""

    prob_hit: float = 0.7  # update of an end-point voxel
    prob_miss: float = 0.4  # update of a voxel a ray passes through
    clamp_min: float = 0.12  # log-odds are clamped to [logit(clamp_min), logit(clamp_max)]
    clamp_max: float = 0.97
    occupancy_thres: float = 0.5  # occupied iff probability >= this

    def problem(self) -> tuple[str, str] | None:
        """The first thing wrong as (what, why), or None for a usable model."""
        for name in PROBABILITIES:
            p = getattr(self, name)
            if not (np.isfinite(p) and 0.0 < p < 1.0):
                return name, f"must be a probability in (0, 1), got {p}"
        if not (self.prob_miss < self.occupancy_thres < self.prob_hit):
            return "sensor model", "needs prob_miss < occupancy_thres < prob_hit"
        if not (self.clamp_min < self.occupancy_thres < self.clamp_max):
            return "clamping", "needs clamp_min < occupancy_thres < clamp_max"
        return None

    def check(self, resolution: float) -> None:
        """Raise MapError for a non-positive `resolution` or an unusable model (both backends call it)."""
        if not (np.isfinite(resolution) and resolution > 0):
            raise MapError(f"octree resolution must be a positive number, got {resolution}")
        wrong = self.problem()
        if wrong is not None:
            raise MapError(f"octree {wrong[0]} {wrong[1]}")

    def logodds(self) -> LogOdds:
        """The model's float32 log-odds, as OctoMap computes them from the probabilities."""
        return LogOdds(logodds(self.prob_hit), logodds(self.prob_miss), logodds(self.clamp_min),
                       logodds(self.clamp_max), logodds(self.occupancy_thres))
