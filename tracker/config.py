"""Tracker settings."""

from __future__ import annotations

from dataclasses import dataclass

from octolog.errors import ConfigError


BACKENDS = ("native", "orbslam3")


@dataclass(frozen=True)
class TrackerConfig:
    n_features: int = 1000
    # live: when frames queue up, track the newest and skip the older ones (each skip is published
    # as a SKIPPED status, so the session log says exactly which frames were consumed)
    live: bool = False
    # pad each frame's processing to at least this long: rehearse a slower machine (0: off)
    throttle_ms: float = 0.0
    # stages that must be up before this one announces itself (e.g. "mapper" when run by hand)
    wait_for: tuple[str, ...] = ()
    wait_timeout_s: float = 60.0
    # compress keyframes on the wire (tracker/keyframe/compressed): "" or "raw" (default), or
    # COLOUR[,png] with COLOUR jpeg[:QUALITY] or png[:LEVEL] (see replay.wire_compression)
    wire_compression: str = ""
    # "native" (ours, deterministic) or "orbslam3" (pyorbslam3, an extra: for comparison)
    backend: str = "native"
    # orbslam3: DBoW2 text vocabulary (`octolog vocab build`); empty: $OCTOLOG_ORB_VOCABULARY
    vocabulary: str = ""

    def validate(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"tracker.backend {self.backend!r}: want one of {', '.join(BACKENDS)}")
        if self.throttle_ms < 0:
            raise ConfigError(f"tracker.throttle_ms {self.throttle_ms}: want >= 0")
        if self.n_features < 100:
            raise ConfigError(f"tracker.n_features {self.n_features}: want >= 100")
        from schemas.codec import parse_wire_compression

        try:
            parse_wire_compression(self.wire_compression)
        except ConfigError as exc:
            raise ConfigError(f"tracker.wire_compression: {exc}") from None


def make_odometry(cfg: TrackerConfig):  # -> RgbdOdometry | OrbSlam3Odometry
    if cfg.backend == "orbslam3":
        from tracker.orbslam3 import OrbSlam3Odometry

        return OrbSlam3Odometry(cfg.vocabulary, n_features=cfg.n_features)
    from tracker.odometry import RgbdOdometry

    return RgbdOdometry(n_features=cfg.n_features)
