"""Tracker settings."""

from __future__ import annotations

from dataclasses import dataclass

from octolog.errors import ConfigError


@dataclass(frozen=True)
class TrackerConfig:
    n_features: int = 1000
    # stages that must be up before this one announces itself (e.g. "mapper" when run by hand)
    wait_for: tuple[str, ...] = ()
    wait_timeout_s: float = 60.0

    def validate(self) -> None:
        if self.n_features < 100:
            raise ConfigError(f"tracker.n_features {self.n_features}: want >= 100")


def make_odometry(cfg: TrackerConfig):  # -> RgbdOdometry
    from tracker.odometry import RgbdOdometry

    return RgbdOdometry(n_features=cfg.n_features)
