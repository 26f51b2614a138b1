"""Replay settings: what to play, how fast, which part, under which topic names."""

from __future__ import annotations

from dataclasses import dataclass

from octolog.kit.calibration import is_calibration_file
from octolog.kit.errors import ConfigError
from octolog.kit.tum import TUM_CAMERAS
from octolog.schemas.wirecompression import parse_wire_compression
from octolog.schemas.topics import Topic


@dataclass(frozen=True)
class ReplayConfig:
    source: str = "synthetic"
    # 0: lockstep, as fast as the tracker consumes (lossless, deterministic); r > 0: r x sensor rate
    rate: float = 0.0
    # lockstep: frames published but not yet acknowledged by the tracker
    window: int = 2
    start: int = 0
    end: int = -1  # -1: to the end
    # stages that must be up before the first frame is published
    # what to publish from an MCAP source: "camera" frames, or the logged "tracker" output
    # (keyframes and pose corrections, standing in for the tracker so a fresh mapper can rebuild)
    play: str = "camera"
    # MCAP source: only the frames the logged tracker consumed (a live tracker skips frames)
    only_consumed: bool = False
    # play every N-th frame of the source only (3: the same camera moving 3x faster, at a third of
    # the frame rate; a fast-motion test case)
    every: int = 1
    # with every > 1: stamp the frames `every` times closer (sensor time / every, ground truth too),
    # so they play at the source's own frame rate: the camera `every` times faster at the same rate
    retime: bool = False
    loop: int = 1  # play the source this many times (sequence numbers keep counting)
    # sensor-time window, seconds from the first frame (-1: unbounded); combines with start/end frames
    start_s: float = -1.0
    end_s: float = -1.0
    # added to every frame's sensor stamp: e.g. the two halves of one sequence replayed as two robots
    # working at the same time (tests/mapper/test_fleet.py); 0 keeps the source's time
    time_shift_s: float = 0.0
    # publish under other topic names: "camera/rgbd=cam2/rgbd" (namespaces: the --namespace flag)
    remap: tuple[str, ...] = ()
    # frames on the wire: "source" (default): as the source encodes them (TUM PNGs, a log's
    # compressed frames) on camera/rgbd/compressed, never decoded on the way, else raw on camera/rgbd;
    # "" or "raw": decoded, raw; COLOUR[,DEPTH] with COLOUR jpeg[:QUALITY] (lossy) or png[:LEVEL]:
    # re-encoded on camera/rgbd/compressed; DEPTH png (default) or zstd, both lossless
    wire_compression: str = "source"
    wait_for: tuple[str, ...] = ("tracker",)
    # the camera of a tum: source whose folder name does not say it (freiburg1, freiburg2, freiburg3),
    # or a calibration file (kit/calibration.py: intrinsics, distortion, depth scale, readout) for a
    # tum: folder or an mcap: recording without CameraInfo; "": from the name, and an error when the
    # name says none (never a silent default)
    camera: str = ""
    # an mcap: recording with colour and depth on topics of their own: images closer than this pair
    # into a frame (TUM's 20 ms by default; a RealSense recording whose streams were not synchronised
    # needs more). TUM folders pair at 20 ms, as TUM's tools do
    pair_ms: float = 20.0
    wait_timeout_s: float = 60.0

    def validate(self) -> None:
        """The one check of the replay settings, run where the config is read (the source spec is
        checked by sources.open_source: the shell sets `source` after loading, from --source)."""
        if self.rate < 0:
            raise ConfigError(f"replay.rate {self.rate}: want 0 (lockstep) or a positive factor")
        if self.camera and self.camera not in TUM_CAMERAS and not is_calibration_file(self.camera):
            raise ConfigError(f"replay.camera {self.camera!r}: want one of {', '.join(TUM_CAMERAS)}, a calibration "
                              f"file (.toml), or unset")
        if self.window < 1:
            raise ConfigError(f"replay.window {self.window}: want >= 1")
        if self.play not in ("camera", "tracker"):
            raise ConfigError(f"replay.play {self.play!r}: want camera or tracker")
        if self.every < 1:
            raise ConfigError(f"replay.every {self.every}: want >= 1")
        if self.loop < 1:
            raise ConfigError(f"replay.loop {self.loop}: want >= 1")
        if not 0 < self.pair_ms <= 1000:
            raise ConfigError(f"replay.pair_ms {self.pair_ms}: want more than 0 and at most 1000 ms")
        for item in self.remap:
            if item.count("=") != 1 or not all(item.split("=")):
                raise ConfigError(f"replay.remap {item!r}: want FROM=TO topic names")
        if self.start < 0:
            raise ConfigError(f"replay.start {self.start}: want >= 0")
        if not abs(self.time_shift_s) < 1e9:
            raise ConfigError(f"replay.time_shift_s {self.time_shift_s}: want a finite number of seconds")
        try:
            parse_wire_compression(self.wire_compression)
        except ConfigError as exc:
            raise ConfigError(f"replay.wire_compression: {exc}") from None


def remapped(topic: Topic, remap: tuple[str, ...]) -> Topic:
    """`topic` under the name `remap` gives it, if any (same message type)."""
    table = dict(item.split("=", 1) for item in remap)
    name = table.get(topic.name)
    return Topic(name.strip("/"), topic.msgtype) if name else topic
