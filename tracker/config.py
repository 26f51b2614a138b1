"""Tracker settings."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from octolog.kit.errors import ConfigError

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
    # native back end: local bundle adjustment over the newest `ba_window` keyframes, loop closing
    # (place recognition + pose graph), relocalisation after tracking loss. `background` runs the
    # back end in a worker process; results are applied at the next keyframe either way, so the
    # outputs are byte-identical with it on or off.
    local_ba: bool = True
    ba_window: int = 5
    # the bundle adjustment at the end of the stream: over every keyframe up to this many, else over
    # the newest this many with the keyframes that made their points held (bounded time and
    # memory on long sessions); 0: none
    global_ba_keyframes: int = 500
    loop_closing: bool = True
    relocalise: bool = True
    background: bool = True
    # a DBoW2 text vocabulary (`octolog vocab build`). orbslam3: required (empty:
    # $OCTOLOG_ORB_VOCABULARY); native: optional, a bag-of-words index over it picks loop and
    # relocalisation candidates (else every keyframe is voted on)
    vocabulary: str = ""
    # native: the colour camera's rolling-shutter readout time, first row to last (ms); 0 = global
    # shutter (D455 colour, the synthetic scene). Unset (the default): `octolog run` and the
    # benchmarks take it from the source (TUM freiburg1: 20 ms, see docs/architecture.md), else 0.
    rolling_shutter_ms: float | None = None

    def validate(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"tracker.backend {self.backend!r}: want one of {', '.join(BACKENDS)}")
        if self.throttle_ms < 0:
            raise ConfigError(f"tracker.throttle_ms {self.throttle_ms}: want >= 0")
        if self.ba_window < 1:
            raise ConfigError(f"tracker.ba_window {self.ba_window}: want >= 1")
        if self.global_ba_keyframes < 0:
            raise ConfigError(f"tracker.global_ba_keyframes {self.global_ba_keyframes}: want >= 0 (0: none)")
        if self.rolling_shutter_ms is not None and not 0.0 <= self.rolling_shutter_ms <= 100.0:
            raise ConfigError(f"tracker.rolling_shutter_ms {self.rolling_shutter_ms}: want 0 to 100 (0 = global shutter)")
        if self.n_features < 100:
            raise ConfigError(f"tracker.n_features {self.n_features}: want >= 100")
        from octolog.schemas.codec import parse_wire_compression

        try:
            parse_wire_compression(self.wire_compression)
        except ConfigError as exc:
            raise ConfigError(f"tracker.wire_compression: {exc}") from None


def for_source(cfg: TrackerConfig, source) -> TrackerConfig:
    """`cfg` with an unset rolling_shutter_ms taken from the source's camera (`readout_s`)."""
    if cfg.rolling_shutter_ms is not None:
        return cfg
    return dataclasses.replace(cfg, rolling_shutter_ms=1e3 * float(source.readout_s))


def make_odometry(cfg: TrackerConfig):  # -> RgbdOdometry | OrbSlam3Odometry
    if cfg.backend == "orbslam3":
        from octolog.tracker.orbslam3 import OrbSlam3Odometry

        return OrbSlam3Odometry(cfg.vocabulary, n_features=cfg.n_features)
    from octolog.tracker.odometry import RgbdOdometry

    vocabulary = None
    if cfg.vocabulary:  # native: loop and relocalisation candidates from a bag-of-words index
        from octolog.tracker.vocab import load

        vocabulary = load(cfg.vocabulary)
    return RgbdOdometry(n_features=cfg.n_features, local_ba=cfg.local_ba, ba_window=cfg.ba_window,
                        global_ba_keyframes=cfg.global_ba_keyframes,
                        loop_closing=cfg.loop_closing, relocalise=cfg.relocalise, background=cfg.background,
                        vocabulary=vocabulary, readout_s=(cfg.rolling_shutter_ms or 0.0) / 1e3)
