"""The replay process: frames from a source onto the bus, in lockstep or at a sensor-time rate."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from octolog.kit.bus import Bus, BusConfig, Received
from octolog.kit.config import to_dict
from octolog.kit.errors import ConfigError, InputError
from octolog.kit.geometry import EncodedRgbd, RgbdFrame
from octolog.kit.mcaplog import damaged, read_wire, summarize
from octolog.kit.tftree import LINK_FROM_OPTICAL
from octolog.kit.viz import Viz
from octolog.replay import source_gravity
from octolog.replay.imu import ImuFeed, source_imu, source_imu_noise
from octolog.replay.config import ReplayConfig, remapped
from octolog.replay.sources import McapSource, Source, TumSource, open_source
from octolog.schemas import checks, codec, posemsgs, rgbdmsgs, streammsgs, wirecompression
from octolog.schemas.topics import (
    ACCEL,
    CAMERA_PROPERTIES,
    GRAVITY,
    CONFIGS,
    GYRO,
    KEYFRAME,
    KEYFRAME_COMPRESSED,
    KEYFRAME_END,
    KEYFRAME_POSES,
    MAP_UPDATE,
    RGBD,
    RGBD_COMPRESSED,
    RGBD_END,
    TF_STATIC,
    TRACKER_GRAVITY,
    TRACKING_STATUS,
)


@dataclass
class ReplayStatus:
    """What the replay sees of the pipeline while it plays: its own rate and, from the tracker's
    statuses and the mapper's updates on the bus, each stage's progress and queue."""

    published: int = 0
    total: int = 0
    elapsed_s: float = 0.0
    sensor_s: float = 0.0  # sensor time played so far
    tracked: int = 0  # statuses received (skipped frames included)
    skipped: int = 0  # frames the tracker skipped to stay real-time (live mode)
    keyframes: int = 0
    mapped: int = 0  # keyframes the mapper has integrated
    tracker_ms: float = 0.0  # the tracker's time on its last frame
    mapper_ms: float = 0.0  # the mapper's time on its last keyframe

    def feed(self, r: Received) -> None:
        if r.topic == TRACKING_STATUS:
            st = r.decode()
            self.tracked += 1
            if st.state == _SKIPPED:
                self.skipped += 1
            else:
                self.tracker_ms = float(st.processing_ms)
            self.keyframes += bool(st.is_keyframe)
        elif r.topic == MAP_UPDATE:
            self.mapped += 1
            self.mapper_ms = float(r.decode().processing_ms)

    def line(self) -> str:
        """One status line: frames, frames/s, real-time factor; per stage its queue (and skips)."""
        fps = self.published / self.elapsed_s if self.elapsed_s > 0 else 0.0
        rtf = self.sensor_s / self.elapsed_s if self.elapsed_s > 0 else 0.0
        left = (self.total - self.published) / fps if fps > 0 else 0.0
        return (f"{self.published}/{self.total} frames {fps:5.1f} fps  RTF {rtf:4.2f} | tracker "
                f"{self.published - self.tracked} queued, {self.skipped} skipped, {self.tracker_ms:3.0f} ms | mapper "
                f"{self.keyframes - self.mapped} queued, {self.mapped} kf, {self.mapper_ms:3.0f} ms | {left:4.0f} s left")


Progress = Callable[[ReplayStatus], None]


_SKIPPED = codec.msgtype(TRACKING_STATUS.msgtype).SKIPPED


@dataclass(frozen=True)
class ReplayResult:
    frames: int
    wall_s: float
    duration_s: float


class Pacer:
    """Decides when the next frame may go: lockstep credit window or sensor-time rate."""

    def __init__(self, bus: Bus, cfg: ReplayConfig, status: ReplayStatus) -> None:
        self.bus, self.cfg, self.status = bus, cfg, status
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
            while (r := self.bus.receive_nowait()) is not None:  # the status line's figures, if subscribed
                self.status.feed(r)

    def finish(self, published: int) -> None:
        if self.cfg.rate == 0:
            while self.acked < published:
                self._drain()

    def _drain(self) -> None:
        r = self.bus.receive()
        if r is not None:
            self.status.feed(r)
            self.acked += r.topic == TRACKING_STATUS


def run(cfg: ReplayConfig, bus_cfg: BusConfig, *, rerun: str = "off", recording_id: str = "octolog",
        progress: Progress | None = None) -> ReplayResult:
    if cfg.play == "tracker":
        return play_tracker_log(cfg, bus_cfg)
    source = open_source(cfg.source, only_consumed=cfg.only_consumed, camera=cfg.camera, every=cfg.every,
                         retime=cfg.retime, pair_ms=cfg.pair_ms)
    with Bus(bus_cfg, "replay") as bus, Viz(rerun, "replay", recording_id) as viz:
        return publish(source, cfg, bus, viz, progress)


def looped(source: Source, cfg: ReplayConfig, *, encoded: bool = False) -> Iterator[RgbdFrame | EncodedRgbd]:
    """The source's frames `cfg.loop` times (still encoded with `encoded`); later passes keep sequence
    numbers and time moving on."""
    end = None if cfg.end < 0 else cfg.end
    shift_seq, shift_ns = 0, round(cfg.time_shift_s * 1e9)
    t0: int | None = None
    for _ in range(cfg.loop):
        first = last = None
        for frame in (source.encoded_frames if encoded else source.frames)(cfg.start, end):
            t0 = frame.stamp_ns if t0 is None else t0
            rel_s = (frame.stamp_ns - t0) * 1e-9
            if cfg.start_s >= 0 and rel_s < cfg.start_s:
                continue
            if cfg.end_s >= 0 and rel_s > cfg.end_s:
                break
            first = first or frame
            last = frame
            yield frame if not (shift_seq or shift_ns) else dataclasses.replace(
                frame, seq=frame.seq + shift_seq, stamp_ns=frame.stamp_ns + shift_ns)
        if first is None or last is None:
            return
        span = last.stamp_ns - first.stamp_ns
        n = last.seq - first.seq + 1
        shift_seq += n
        shift_ns += span + (span // (n - 1) if n > 1 else 33_333_333)


def publish(source: Source, cfg: ReplayConfig, bus: Bus, viz: Viz, progress: Progress | None) -> ReplayResult:
    wire = wirecompression.parse_wire_compression(cfg.wire_compression)
    # as the source has them: encoded images go out untouched (the tracker decodes them once)
    passthrough = cfg.wire_compression == wirecompression.SOURCE and source.encoded
    compressed = passthrough or wire is not None
    frames_pub = bus.publisher(remapped(RGBD_COMPRESSED if compressed else RGBD, cfg.remap))
    end_pub = bus.publisher(remapped(RGBD_END, cfg.remap))
    props_pub = bus.publisher(remapped(CAMERA_PROPERTIES, cfg.remap))
    # lockstep needs the tracker's statuses; the status line shows them and the mapper's updates
    watched = ([TRACKING_STATUS] if cfg.rate == 0 else []) + ([TRACKING_STATUS, MAP_UPDATE] if progress else [])
    bus.start(list(dict.fromkeys(watched)), wait_for=cfg.wait_for, timeout_s=cfg.wait_timeout_s)
    bus.watch(["tracker"], required=False)  # see the end
    bus.publisher(CONFIGS["replay"]).put(streammsgs.config_msg("replay", to_dict(cfg)))
    # before the first frame, which depends on it (wire numbering): a tracker anywhere knows the camera
    props_pub.put(streammsgs.camera_properties_msg(source.name, source.readout_s, depth=source.depth_model,
                                                   imu_noise=source_imu_noise(source)))
    end = None if cfg.end < 0 else cfg.end
    total = max(0, min(len(source), end if end is not None else len(source)) - cfg.start) * cfg.loop
    status = ReplayStatus(total=total)
    pacer = Pacer(bus, cfg, status)
    t0 = time.monotonic()
    first_stamp = last_stamp = None
    # up at frame 0, for a mapper not told `grid_up` (one that runs elsewhere); a window starting
    # later has no accelerometer reading at its first frame here
    up = source_gravity.source_up(source) if cfg.start == 0 else None
    up_bytes: list[bytes] = []  # what a mapper's `get` on camera/gravity receives (nothing: no up)
    bus.serve(GRAVITY, lambda: up_bytes[0] if up_bytes else None)
    viz.text("replay/events", f"replaying {source.name}: {total} frames")  # the images: the tracker logs them
    imu = imu_feed(source, cfg, bus)
    for frame in looped(source, cfg, encoded=passthrough):
        pacer.wait(frames_pub.count, frame.stamp_ns)
        imu.before(frame.seq, frame.stamp_ns)
        if frames_pub.count == 0:  # the camera's own frames, before its first image (the tracker hangs world on their root)
            bus.publisher(TF_STATIC).put(posemsgs.tf_msg(camera_tree(source, frame.frame_id), frame.stamp_ns))
            if up is not None:
                up_bytes.append(bus.publisher(GRAVITY).put(posemsgs.vector3_stamped_msg(up[0], frame.stamp_ns,
                                                                                    frame.frame_id)))
        if passthrough:  # as the source stored them: checked as every receiver will (a bad one would be dropped)
            msg = rgbdmsgs.encoded_rgbd_msg(frame)
            try:
                checks.check(msg, frames_pub.topic.msgtype)
            except InputError as exc:
                raise InputError(f"{source.name}: frame {frame.seq}: {exc}") from None
            frames_pub.put(msg)
        else:
            frames_pub.put(rgbdmsgs.rgbd_msg(frame) if wire is None else rgbdmsgs.compressed_rgbd_msg(frame, wire))
        first_stamp = frame.stamp_ns if first_stamp is None else first_stamp
        last_stamp = frame.stamp_ns
        if progress is not None:
            status.published, status.elapsed_s = frames_pub.count, time.monotonic() - t0
            status.sensor_s = (last_stamp - first_stamp) * 1e-9
            progress(status)
    pacer.finish(frames_pub.count)
    end_pub.put(streammsgs.stream_end_msg(frames_pub.topic.name, frames_pub.count, last_stamp or 0))
    wall_s = time.monotonic() - t0
    # stay (histories and all) until the tracker has taken every frame: a tracker far behind would
    # otherwise see its source gone before the end and, after peer_timeout_s, take it for dead
    bus.linger("tracker", status.feed)
    duration = ((last_stamp or 0) - (first_stamp or 0)) * 1e-9
    return ReplayResult(frames_pub.count, wall_s, duration)


def imu_feed(source: Source, cfg: ReplayConfig, bus: Bus) -> ImuFeed:
    """The source's IMU samples up to each frame, sent just before it (a looped replay has none:
    its time jumps back)."""
    return ImuFeed(source_imu(source) if cfg.loop == 1 else None, bus.publisher(remapped(GYRO, cfg.remap)),
                   bus.publisher(remapped(ACCEL, cfg.remap)), round(cfg.time_shift_s * 1e9))


def camera_tree(source: Source, frame_id: str) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, parent_from_child) of the camera's static frames: a recording's own (its
    /tf_static), else `camera_link` -> the images' optical frame (REP 103's axes)."""
    inner = getattr(source, "inner", source)  # a Subsampled source: the camera is the inner one's
    recorded = inner.static_transforms() if isinstance(inner, McapSource) else []
    if recorded:
        return recorded
    imu = source_imu(source) if isinstance(inner, TumSource) else None  # a calibration file may place its IMU
    placed = [(frame_id, imu.frame_id, imu.camera_from_imu)] if imu is not None and imu.camera_from_imu is not None else []
    return [("camera_link", frame_id, LINK_FROM_OPTICAL), *placed]


def play_tracker_log(cfg: ReplayConfig, bus_cfg: BusConfig) -> ReplayResult:
    """Stand in for the tracker: publish its logged keyframes and pose corrections, in log order; with
    `start`/`end`, only the keyframes made from frames in that window (the corrections all: a mapper
    passes over the ids it does not have). At once (`rate` 0), or each at its sensor stamp played
    `rate` times faster than the camera took it (a mapper's capacity, bench/mapper_rates.py)."""
    kind, _, path = cfg.source.partition(":")
    if kind != "mcap" or not path:
        raise ConfigError(f"replay.play = tracker needs an mcap:PATH source, got {cfg.source!r}")
    summary = summarize(path)
    if not summary.complete:
        raise InputError(damaged(path, summary.problem))
    kf_topic = KEYFRAME if KEYFRAME.name in summary.topics else KEYFRAME_COMPRESSED
    if kf_topic.name not in summary.topics:
        raise InputError(f"{path}: no /{KEYFRAME.name} topic: nothing to feed a mapper with")
    t0 = time.monotonic()
    with Bus(bus_cfg, "tracker") as bus:
        up = (TRACKER_GRAVITY,) if TRACKER_GRAVITY.name in summary.topics else ()  # the IMU's up, in order
        pubs = {t.name: bus.publisher(remapped(t, cfg.remap)) for t in (kf_topic, KEYFRAME_POSES, *up)}
        end_pub = bus.publisher(remapped(KEYFRAME_END, cfg.remap))
        bus.start([], wait_for=cfg.wait_for, timeout_s=cfg.wait_timeout_s)
        bus.watch(["mapper"], required=False)  # as the tracker: keyframes stay until the mapper is done
        windowed = cfg.start > 0 or cfg.end >= 0
        first_ns: int | None = None
        wall0 = time.monotonic()
        for i, m in enumerate(read_wire(path, list(pubs))):
            try:
                checks.checked(m.data, pubs[m.topic].topic.msgtype)  # as the mapper's bus will
            except InputError as exc:
                raise InputError(f"{path}: message {i} on /{m.topic}: {exc}") from None
            if windowed and m.topic == kf_topic.name:
                seq = int(codec.decode(m.data, m.msgtype).frame_seq)
                if seq < cfg.start or 0 <= cfg.end <= seq:
                    continue
            if cfg.rate > 0:  # paced by the items' sensor stamps
                stamp = codec.stamp_ns(codec.decode(m.data, m.msgtype).header)
                first_ns = stamp if first_ns is None else first_ns
                time.sleep(max(0.0, wall0 + (stamp - first_ns) * 1e-9 / cfg.rate - time.monotonic()))
            pubs[m.topic].put_raw(m.data)
        end_pub.put(streammsgs.stream_end_msg(KEYFRAME_POSES.name, pubs[KEYFRAME_POSES.name].count))
        end_pub.put(streammsgs.stream_end_msg(kf_topic.name, pubs[kf_topic.name].count))
        bus.linger("mapper")
    return ReplayResult(pubs[kf_topic.name].count, time.monotonic() - t0, 0.0)
