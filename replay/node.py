"""The replay process: frames from a source onto the bus, in lockstep or at a sensor-time rate."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from octolog.bus import Bus, BusConfig
from octolog.viz import Viz
from replay.config import ReplayConfig
from replay.sources import Source, open_source
from schemas import codec
from schemas.topics import RGBD, RGBD_END, TRACKING_STATUS

Progress = Callable[[int, int, float], None]  # (frames done, total, seconds elapsed)


@dataclass(frozen=True)
class ReplayResult:
    frames: int
    wall_s: float
    duration_s: float


class Pacer:
    """Decides when the next frame may go: lockstep credit window or sensor-time rate."""

    def __init__(self, bus: Bus, cfg: ReplayConfig) -> None:
        self.bus, self.cfg = bus, cfg
        self.acked = 0
        self._t0_wall: float | None = None
        self._t0_stamp = 0

    def wait(self, published: int, stamp_ns: int) -> None:
        if self.cfg.rate == 0:
            while published - self.acked >= self.cfg.window:
                self._drain()
        else:
            if self._t0_wall is None:
                self._t0_wall, self._t0_stamp = time.monotonic(), stamp_ns
            due = self._t0_wall + (stamp_ns - self._t0_stamp) * 1e-9 / self.cfg.rate
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def finish(self, published: int) -> None:
        if self.cfg.rate == 0:
            while self.acked < published:
                self._drain()

    def _drain(self) -> None:
        r = self.bus.receive()
        if r is not None and r.topic == TRACKING_STATUS:
            self.acked += 1


def run(cfg: ReplayConfig, bus_cfg: BusConfig, *, rerun: str = "off", recording_id: str = "octolog",
        progress: Progress | None = None) -> ReplayResult:
    source = open_source(cfg.source)
    with Bus(bus_cfg, "replay") as bus, Viz(rerun, "replay", recording_id) as viz:
        return publish(source, cfg, bus, viz, progress)


def publish(source: Source, cfg: ReplayConfig, bus: Bus, viz: Viz, progress: Progress | None) -> ReplayResult:
    frames_pub = bus.publisher(RGBD)
    end_pub = bus.publisher(RGBD_END)
    bus.start([TRACKING_STATUS] if cfg.rate == 0 else [], wait_for=cfg.wait_for, timeout_s=cfg.wait_timeout_s)
    pacer = Pacer(bus, cfg)
    end = None if cfg.end < 0 else cfg.end
    total = max(0, min(len(source), end if end is not None else len(source)) - cfg.start)
    t0 = time.monotonic()
    first_stamp = last_stamp = None
    for frame in source.frames(cfg.start, end):
        pacer.wait(frames_pub.count, frame.stamp_ns)
        frames_pub.put(codec.rgbd_msg(frame))
        first_stamp = frame.stamp_ns if first_stamp is None else first_stamp
        last_stamp = frame.stamp_ns
        if viz.enabled:
            viz.set_time(frame.stamp_ns, frame.seq)
            if frames_pub.count == 1:
                viz.camera("camera/rgbd", frame.intrinsics)
            viz.rgb("camera/rgbd/color", frame.rgb)
            viz.depth("camera/rgbd/depth", frame.depth, frame.depth_scale_m)
        if progress is not None:
            progress(frames_pub.count, total, time.monotonic() - t0)
    pacer.finish(frames_pub.count)
    end_pub.put(codec.stream_end_msg(RGBD.name, frames_pub.count, last_stamp or 0))
    duration = ((last_stamp or 0) - (first_stamp or 0)) * 1e-9
    return ReplayResult(frames_pub.count, time.monotonic() - t0, duration)
