"""The session logger: every pipeline topic, as published on the bus, into one MCAP file.

It runs as its own process (`octolog log`), subscribes before the source starts, and finishes
when every stream has ended: the counts announced by the end-of-stream messages are all in.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from octolog.bus import Bus, BusConfig
from octolog.mcaplog import McapWriter
from schemas import topics as T


@dataclass
class LogResult:
    counts: dict[str, int] = field(default_factory=dict)
    path: str = ""


# Which data topics each end-of-stream message closes, and how their counts relate.
def _expected(ends: dict[str, int]) -> dict[str, int] | None:
    if not {T.RGBD_END.name, T.KEYFRAME_END.name, T.MAP_END.name} <= set(ends):
        return None
    frames, kfs = ends[T.RGBD_END.name], ends[T.KEYFRAME_END.name]
    return {T.RGBD.name: frames, T.TRACKING_STATUS.name: frames, T.KEYFRAME.name: kfs,
            T.MAP_UPDATE.name: ends[T.MAP_END.name]}


def run(bus_cfg: BusConfig, out: Path, *, compression: str = "zstd", metadata: dict[str, dict[str, str]] | None = None,
        stages: tuple[str, ...] = ("replay", "tracker", "mapper")) -> LogResult:
    result = LogResult(path=str(out))
    with Bus(bus_cfg, "log", inbox_size=16) as bus, McapWriter(out, compression=compression) as mcap:
        for name, data in (metadata or {}).items():
            mcap.add_metadata(name, data)
        bus.subscribe(T.ALL)
        bus.announce()
        bus.watch(stages)
        ends: dict[str, int] = {}
        while True:
            expected = _expected(ends)
            if expected is not None and all(result.counts.get(k, 0) >= v for k, v in expected.items()):
                break
            r = bus.receive()
            if r is None:
                continue
            now = time.time_ns()
            mcap.write(r.topic.name, r.topic.msgtype, r.payload, log_time_ns=now, publish_time_ns=now)
            result.counts[r.topic.name] = result.counts.get(r.topic.name, 0) + 1
            if r.topic in (T.RGBD_END, T.KEYFRAME_END, T.MAP_END):
                ends[r.topic.name] = int(r.decode().count)
                producer = {T.RGBD_END: "replay", T.KEYFRAME_END: "tracker", T.MAP_END: "mapper"}[r.topic]
                bus.unwatch(producer)
    return result
