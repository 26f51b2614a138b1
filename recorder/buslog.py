"""The session logger: every pipeline topic, as published on the bus, into one MCAP file.

Messages of standard types are written as they came; those of octolog's own types as standard-typed
parts (octolog.schemas.logview), so viewers and rosbags read the whole log, and a replay joins them
back into the same bytes.

It runs as its own process (`octolog log`), subscribes before the source starts, and finishes when
every producer has sent its end-of-stream message. A producer's end message travels behind all its
data on the same link, so at that moment the logger holds everything that producer sent, or knows
exactly how much went missing.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.bus import Bus, BusConfig
from octolog.kit.config import to_toml
from octolog.kit.errors import StageError
from octolog.kit.mcaplog import McapWriter
from octolog.kit.metrics import write_tum
from octolog.schemas import codec, logview, posemsgs
from octolog.schemas import topics as T

# end message -> (producing stage, the data topics it may close: the one its `topic` field names,
# raw or compressed, else the first)
ENDS = {
    T.RGBD_END: ("replay", (T.RGBD, T.RGBD_COMPRESSED)),
    # the tracker ends its trajectory and keyframe_poses first, then its keyframes
    T.KEYFRAME_END: ("tracker", (T.KEYFRAME, T.KEYFRAME_COMPRESSED, T.KEYFRAME_POSES, T.TRAJECTORY)),
    T.MAP_END: ("mapper", (T.MAP_UPDATE,)),
}


def _standard(topic: T.Topic, payload: bytes, checked: set[str]) -> list[tuple[str, str, bytes]]:
    """The message as the log stores it (standard types, octolog.schemas.logview); the first of each
    topic is joined back and compared, so a log that would not replay byte for byte fails at once."""
    parts = logview.split(topic.name, topic.msgtype, payload)
    if (len(parts) > 1 or parts[0][1] != topic.msgtype) and topic.name not in checked:
        joined = logview.join(topic.msgtype, parts[-1][2], {name: data for name, _, data in parts[:-1]})
        if joined != payload:
            raise StageError(f"/{topic.name}: its standard-typed log form does not rebuild the message")
        checked.add(topic.name)
    return parts


_SKIPPED = codec.msgtype(T.TRACKING_STATUS.msgtype).SKIPPED


@dataclass
class StatusTally:
    """The tracker's statuses as the log holds them: frames consumed (tracked, lost or placed by the
    IMU) and skipped, and the first and last status stamps (sensor time; 0 before any). Counted as
    they are written, so the run's summary need not read the whole log back for them."""

    consumed: int = 0
    skipped: int = 0
    first_ns: int = 0
    last_ns: int = 0

    def add(self, msg: Any) -> None:
        """One status (a decoded TrackingStatus)."""
        t = codec.stamp_ns(msg.header)
        first = not (self.consumed or self.skipped)
        self.first_ns = t if first else min(self.first_ns, t)
        self.last_ns = t if first else max(self.last_ns, t)
        if msg.state == _SKIPPED:
            self.skipped += 1
        else:
            self.consumed += 1


@dataclass
class LogResult:
    counts: dict[str, int] = field(default_factory=dict)
    path: str = ""
    files: list[str] = field(default_factory=list)
    statuses: StatusTally = field(default_factory=StatusTally)


@dataclass
class _Kept:
    """What the log keeps from the bus besides the file: the stages' configs, the final trajectory,
    the replay's camera/gravity."""

    configs: dict[str, dict] = field(default_factory=dict)
    trajectory: object = None
    up: list[float] | None = None

    def take(self, r: Any) -> None:
        if r.topic in T.CONFIGS.values():
            item = json.loads(r.decode().data)
            self.configs[str(item["stage"])] = item["config"]
        elif r.topic is T.TRAJECTORY:
            self.trajectory = r.decode()
        elif r.topic is T.GRAVITY:
            v = r.decode().vector
            self.up = [float(v.x), float(v.y), float(v.z)]

    def add_metadata(self, mcap: McapWriter, metadata: dict[str, dict[str, str]]) -> None:
        """The configs (and up, where the mapper was not told it) into the file, unless given."""
        configs, up = self.configs, self.up
        if up is not None and not configs.get("mapper", {"grid_up": True}).get("grid_up"):
            # the mapper was not told up: it built `map` on the replay's (mapper/mapframe.py); a
            # replay of this folder gets it the way `octolog run` gives it, in the config
            configs["mapper"]["grid_up"] = up
            if "gravity" not in metadata:
                note = "gravity-aligned (the replay's camera/gravity)"
                mcap.add_metadata("gravity", {"up": json.dumps(up), "note": note})
        if configs and "config" not in metadata:
            mcap.add_metadata("config", {k: json.dumps(v, sort_keys=True) for k, v in sorted(configs.items())})


def run(bus_cfg: BusConfig, out: Path, *, compression: str = "zstd", metadata: dict[str, dict[str, str]] | None = None,
        stages: tuple[str, ...] = ("replay", "tracker", "mapper"), frames: bool = True) -> LogResult:
    """Log until every producer in `stages` has ended. `out`: an MCAP file, or (no `.mcap` suffix) a
    session folder: `session.mcap`, then `config.toml` from the stages' configs on the bus and the
    tracker's `trajectory.txt`, so the folder replays with `octolog replay` wherever it was written.
    Without `frames` the camera frames are not subscribed: on a machine across a link from the
    camera, they then stay on the camera's side (Zenoh routes only what someone subscribes to)."""
    folder = None if out.suffix == ".mcap" else out
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        out = folder / "session.mcap"
    result = LogResult(path=str(out))
    kept = _Kept()
    metadata = dict(metadata or {})
    with Bus(bus_cfg, "log", inbox_size=16) as bus, McapWriter(out, compression=compression) as mcap:
        for name, data in metadata.items():
            mcap.add_metadata(name, data)
        bus.subscribe([t for t in T.ALL if frames or t not in T.FRAMES])
        bus.announce()
        bus.watch(stages)
        # the frames come from a replay, or from a recorder publishing a camera live
        producer = "recorder" if "recorder" in stages else "replay"
        ends = {t: (producer if stage == "replay" else stage, closes) for t, (stage, closes) in ENDS.items()}
        pending = {stage for stage, _ in ends.values() if stage in stages}
        announced: dict[str, int] = {}
        frame_total: int | None = None
        checked: set[str] = set()
        while pending or any(result.counts.get(t, 0) < n for t, n in announced.items()):
            r = bus.receive()
            if r is None:
                for t, n in announced.items():
                    bus.expect_count(T.BY_NAME[t], result.counts.get(t, 0), n)
                continue
            now = time.time_ns()
            for name, msgtype, data in _standard(r.topic, bytes(r.payload), checked):
                mcap.write(name, msgtype, data, log_time_ns=now, publish_time_ns=now)
            result.counts[r.topic.name] = result.counts.get(r.topic.name, 0) + 1
            kept.take(r)
            if r.topic is T.TRACKING_STATUS:
                result.statuses.add(r.decode())
            if r.topic in ends:
                stage, closes = ends[r.topic]
                end = r.decode()
                topic = next((t for t in closes if t.name == end.topic), closes[0])
                if topic in T.FRAMES:
                    frame_total = int(end.count)
                if frames or topic not in T.FRAMES:
                    announced[topic.name] = int(end.count)
                    bus.expect_count(topic, result.counts.get(topic.name, 0), announced[topic.name])
                if topic in (T.KEYFRAME_POSES, T.TRAJECTORY):
                    continue  # the tracker's keyframe end follows
                bus.unwatch(stage)
                pending.discard(stage)
                kfs = [t for t in (T.KEYFRAME, T.KEYFRAME_COMPRESSED) if t.name in announced]
                if {producer, "tracker"} <= set(stages) and frame_total is not None and kfs:
                    announced[T.TRACKING_STATUS.name] = frame_total  # one per frame consumed
        kept.add_metadata(mcap, metadata)
    if folder is not None:
        _leave_session(folder, kept.configs, kept.trajectory, result)
        _write_summary(folder, result, frames)
    return result


def _write_summary(folder: Path, result: LogResult, frames: bool) -> None:
    """summary.json, written last: the folder is complete."""
    summary = {"made_by": "octolog log", "frames_logged": frames, "messages": dict(sorted(result.counts.items())),
               "files": ["session.mcap", *result.files]}
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")


def _leave_session(folder: Path, configs: dict[str, dict], trajectory: object, result: LogResult) -> None:
    """What `octolog replay FOLDER` needs beside the log, and the trajectory."""
    if configs:
        (folder / "config.toml").write_text(to_toml(configs))
        result.files.append("config.toml")
    if trajectory is not None:
        stamps, rows = posemsgs.path_rows(trajectory)
        write_tum(folder / "trajectory.txt", np.asarray(stamps, dtype=np.int64), rows)
        result.files.append("trajectory.txt")
