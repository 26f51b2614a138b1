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

import time
from dataclasses import dataclass, field
from pathlib import Path

from octolog.kit.bus import Bus, BusConfig
from octolog.kit.errors import StageError
from octolog.kit.mcaplog import McapWriter
from octolog.schemas import logview
from octolog.schemas import topics as T

# end message -> (producing stage, the data topics it may close: the one its `topic` field names,
# raw or compressed, else the first)
ENDS = {
    T.RGBD_END: ("replay", (T.RGBD, T.RGBD_COMPRESSED)),
    # the tracker ends its keyframe_poses first, then its keyframes
    T.KEYFRAME_END: ("tracker", (T.KEYFRAME, T.KEYFRAME_COMPRESSED, T.KEYFRAME_POSES)),
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


@dataclass
class LogResult:
    counts: dict[str, int] = field(default_factory=dict)
    path: str = ""


def run(bus_cfg: BusConfig, out: Path, *, compression: str = "zstd", metadata: dict[str, dict[str, str]] | None = None,
        stages: tuple[str, ...] = ("replay", "tracker", "mapper")) -> LogResult:
    result = LogResult(path=str(out))
    with Bus(bus_cfg, "log", inbox_size=16) as bus, McapWriter(out, compression=compression) as mcap:
        for name, data in (metadata or {}).items():
            mcap.add_metadata(name, data)
        bus.subscribe(T.ALL)
        bus.announce()
        bus.watch(stages)
        # the frames come from a replay, or from a recorder publishing a camera live
        producer = "recorder" if "recorder" in stages else "replay"
        ends = {t: (producer if stage == "replay" else stage, closes) for t, (stage, closes) in ENDS.items()}
        pending = {stage for stage, _ in ends.values() if stage in stages}
        announced: dict[str, int] = {}
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
            if r.topic in ends:
                stage, closes = ends[r.topic]
                end = r.decode()
                topic = next((t for t in closes if t.name == end.topic), closes[0])
                announced[topic.name] = int(end.count)
                bus.expect_count(topic, result.counts.get(topic.name, 0), announced[topic.name])
                if topic is T.KEYFRAME_POSES:
                    continue  # the tracker's keyframe end follows
                bus.unwatch(stage)
                pending.discard(stage)
                frames = [announced[t.name] for t in ENDS[T.RGBD_END][1] if t.name in announced]
                kfs = [t for t in (T.KEYFRAME, T.KEYFRAME_COMPRESSED) if t.name in announced]
                if {producer, "tracker"} <= set(stages) and frames and kfs:
                    announced[T.TRACKING_STATUS.name] = frames[0]  # one per frame consumed
    return result
