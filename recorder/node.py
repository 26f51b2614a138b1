"""The recorder process: camera -> MCAP, optionally published live on Zenoh and logged to Rerun.

A capture thread takes frames from the backend and hands Captures to the Recorder (queue, writer
thread); the calling thread only waits, reports status and turns Ctrl-C / SIGTERM into a clean
stop. Live publishing (the camera topics and the paired `camera/rgbd` frame for the tracker) and
Rerun logging run on their own threads behind small queues, so neither can stall the file.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit import depthmodel
from octolog.kit.bus import Bus
from octolog.kit.errors import DeviceLost, RecorderError
from octolog.kit.geometry import EncodedRgbd, RgbdFrame
from octolog.kit.viz import Viz
from octolog.recorder.capture import Backend, Capture, DeviceDescription
from octolog.recorder.config import RecorderConfig, capture_profile, make_backend, make_recorder
from octolog.recorder.frame_converter import FrameConverter
from octolog.recorder.livesink import LiveSink
from octolog.recorder.writer import Recorder
from octolog.recorder.recording_types import (
    Encoded,
    RecorderStatus,
    RecordResult,
    camera_transforms,
    frame_names,
    output_paths,
)
from octolog.schemas import codec, imagecodec, posemsgs, rgbdmsgs, streammsgs, wirecompression
from octolog.schemas import topics as T


def run(cfg: RecorderConfig, out: Path, *, bus_cfg: Any = None, rerun: str = "off", recording_id: str = "octolog",
        duration_s: float = 0.0, overwrite: bool = False, status: Callable[[RecorderStatus], None] | None = None,
        status_interval_s: float = 1.0, backend: Backend | None = None,
        stop: threading.Event | None = None) -> RecordResult:
    """Record until `duration_s` of sensor time, the source ends, `stop` is set or Ctrl-C/SIGTERM.

    Raises RecorderError (after finishing the file) when the camera is lost or writing fails."""
    part = output_paths(out, split=bool(cfg.split_size_mb or cfg.split_duration_s), overwrite=overwrite)
    backend = backend if backend is not None else make_backend(cfg)
    with ExitStack() as stack:
        stack.callback(backend.close)
        device = backend.open(capture_profile(cfg))
        sinks = open_sinks(stack, cfg, device, bus_cfg, rerun, recording_id)
        recorder = make_recorder(cfg, part, device, sinks=sinks, block_when_full=not backend.realtime)
        converter = FrameConverter(align=cfg.aligned_depth, raw_depth=cfg.raw_depth, fps=cfg.color.fps)
        return record(backend, converter, recorder, duration_ns=int(duration_s * 1e9), status=status,
                      status_interval_s=status_interval_s, stop=stop)


def record(backend: Backend, converter: FrameConverter, recorder: Recorder, *, duration_ns: int = 0,
           status: Callable[[RecorderStatus], None] | None = None, status_interval_s: float = 1.0,
           stop: threading.Event | None = None) -> RecordResult:
    """Run the capture thread until done; finish the recorder; raise what went wrong, if anything."""
    stop = stop or threading.Event()
    done = threading.Event()
    outcome: dict[str, Any] = {"reason": "stopped"}

    def capture() -> None:
        try:
            outcome["reason"] = capture_loop(backend, converter, recorder, stop, duration_ns)
        except Exception as exc:  # noqa: BLE001 - re-raised on the calling thread after finishing
            outcome["error"] = exc
        finally:
            done.set()

    thread = threading.Thread(target=capture, name="recorder-capture", daemon=True)
    thread.start()
    try:
        while not done.wait(status_interval_s):
            if status is not None:
                status(recorder.status())
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM turned into one by the CLI: finish cleanly
        stop.set()
        outcome["interrupted"] = True
        done.wait()
    thread.join()
    if outcome.get("interrupted"):
        outcome["reason"] = "interrupted"
    err = outcome.get("error")
    reason = outcome["reason"] if err is None else f"device lost: {err}" if isinstance(err, DeviceLost) else \
        f"error: {err}"
    result = recorder.close(reason)  # raises when writing failed
    if status is not None:
        status(recorder.status())
    if isinstance(err, DeviceLost):
        raise RecorderError(f"{err}: recording stopped after {result.streams['color'].frames} frames; "
                            f"{', '.join(map(str, result.paths))} finished with everything so far") from None
    if err is not None:
        raise err
    return result


def capture_loop(backend: Backend, converter: FrameConverter, recorder: Recorder, stop: threading.Event,
                 duration_ns: int) -> str:
    """Backend frames -> Captures -> recorder, until a stop condition; returns why it stopped."""
    t_end = 0
    while not stop.is_set():
        if recorder.failed.is_set():
            return "write failure"
        frames = backend.wait(0.1)
        if frames is None:
            for cap in converter.flush():
                recorder.submit(cap)
            return "end of stream"
        for item in frames:
            for cap in converter.convert(item):
                if duration_ns:
                    if not t_end:
                        t_end = cap.stamp_ns + duration_ns
                    if cap.stamp_ns >= t_end:
                        return "duration reached"
                recorder.submit(cap)
    for cap in converter.flush():
        recorder.submit(cap)
    return "stopped"


# --- live sinks -------------------------------------------------------------------------------------


def open_sinks(stack: ExitStack, cfg: RecorderConfig, device: DeviceDescription, bus_cfg: Any, rerun: str,
               recording_id: str) -> list[LiveSink]:
    sinks: list[LiveSink] = []
    if bus_cfg is not None:
        bus = stack.enter_context(Bus(bus_cfg, "recorder"))
        pub = BusPublisher(bus, device, frame_names(cfg.frame_prefix), compressed=cfg.color_codec == "jpeg",
                           window=cfg.publish_window, lag_ms=cfg.publish_lag_ms, wire_depth=cfg.wire_depth)
        # a file's replay serves up on camera/gravity; a live camera has none to give (the mapper reads
        # its accelerometer): this queryable says so at once, where no answerer costs an asker its timeout
        bus.serve(T.GRAVITY, lambda: None)
        bus.watch(cfg.wait_for)
        bus.wait_for(cfg.wait_for, cfg.wait_timeout_s)
        sink = LiveSink("bus", pub, size=cfg.live_queue_frames, on_close=pub.end)
        stack.callback(sink.close)  # before the bus closes (callbacks run last-in first-out)
        sinks.append(sink)
    if rerun != "off":
        viz = stack.enter_context(Viz(rerun, "recorder", recording_id))
        sink = LiveSink("rerun", VizLogger(viz, device), size=cfg.live_queue_frames)
        stack.callback(sink.close)
        sinks.append(sink)
    return sinks


class BusPublisher:
    """Publishes each written message on its topic, and colour + aligned depth as `camera/rgbd`."""

    def __init__(self, bus: Any, device: DeviceDescription, frames: dict[str, str], *, compressed: bool = False,
                 window: int = 0, lag_ms: float = 0.0, wire_depth: str = "zstd") -> None:
        self._bus = bus
        self._device = device
        self._frames = frames
        self._frame = frames["color"]
        # the camera's static tree (camera_link, optical frames, IMU), as the recording has it: the
        # session log's TF tree, and what the mapper rotates the accelerometer's up with
        self._tf_static = bus.publisher(T.TF_STATIC)
        self._pubs: dict[str, Any] = {}
        # compressed: the recorded JPEG colour as it was written, depth lossless as `wire_depth` says
        # (the recorded PNG when depth is recorded so), on camera/rgbd/compressed: a tenth of the raw frame
        self.wire_depth = wire_depth
        self._rgbd = bus.publisher(T.RGBD_COMPRESSED if compressed else T.RGBD)
        self._rgbd_end = bus.publisher(T.RGBD_END)
        self._props = bus.publisher(T.CAMERA_PROPERTIES)
        # a live tracker's pace (RecorderConfig.publish_window, publish_lag_ms): frames out, minus
        # statuses back; the stamps of the frames out that no status answered yet
        self.window, self.answered, self.held_back = window, 0, 0
        self._lag_ns = round(lag_ms * 1e6)
        self._unanswered: deque[int] = deque()
        self._warm_up()
        if window:
            bus.listen(T.TRACKING_STATUS, self._answered)
        bus.announce()
        bus.watch(["tracker"], required=False)  # see `end`

    def _warm_up(self) -> None:
        """Each message this publisher makes, made and encoded once on blank data before the camera
        starts: the codec's lazy set-up (~45 ms) then does not hold up the first frame; a late first
        frame comes out with the next ones right behind it, a burst a cold tracker falls behind on."""
        intrinsics, scale = self._device.color, self._device.depth_scale_m
        if intrinsics is None:
            return  # no colour: nothing goes out but the recorded messages as they are
        codec.encode(posemsgs.tf_msg(camera_transforms(self._device, self._frames), 0), T.TF_STATIC.msgtype)
        codec.encode(self._properties(0), T.CAMERA_PROPERTIES.msgtype)
        blank = np.zeros((2, 2), np.uint16)
        if self._rgbd.topic is T.RGBD:
            msg = rgbdmsgs.rgbd_msg(RgbdFrame(0, 0, np.zeros((2, 2, 3), np.uint8), blank, scale, intrinsics, self._frame))
        else:
            msg = rgbdmsgs.encoded_rgbd_msg(EncodedRgbd(0, 0, b"", "jpeg", imagecodec.depth_zstd(blank),
                                                        wirecompression.DEPTH_ZSTD_FORMAT, scale, intrinsics, self._frame))
        codec.encode(msg, self._rgbd.topic.msgtype)

    def _properties(self, stamp_ns: int) -> Any:
        """The camera's properties message: the D455's colour camera has a global shutter; its depth error model."""
        depth = self._device.depth
        model = depthmodel.realsense(self._device.name, depth.fx) if depth is not None else None
        return streammsgs.camera_properties_msg(self._device.name, 0.0, stamp_ns, model)

    def _answered(self, _status: Any) -> None:
        self.answered += 1  # on Zenoh's thread; read by the publishing thread

    def __call__(self, cap: Capture, msgs: list[Encoded]) -> None:
        if self._tf_static.count == 0:
            self._tf_static.put(posemsgs.tf_msg(camera_transforms(self._device, self._frames), cap.stamp_ns))
        for m in msgs:
            if m.topic.name not in self._pubs:
                self._pubs[m.topic.name] = self._bus.publisher(m.topic)
            self._pubs[m.topic.name].put_raw(m.data)
        if cap.color is not None and cap.aligned_depth is not None:
            assert self._device.color is not None
            c, d = cap.color, cap.aligned_depth
            if self._props.count == 0:  # before the first frame
                self._props.put(self._properties(c.stamp_ns))
            if self._behind(c.stamp_ns):
                self.held_back += 1  # the tracker would skip this one
                return
            if self.window:
                self._unanswered.append(c.stamp_ns)
            if self._rgbd.topic is T.RGBD:
                self._rgbd.put(rgbdmsgs.rgbd_msg(RgbdFrame(c.frame_number, c.stamp_ns, c.array, d.array,
                                                        self._device.depth_scale_m, self._device.color, self._frame)))
                return
            written = {m.topic: m for m in msgs}
            colour = codec.decode(written[T.COLOR_JPEG].data, T.COLOR_JPEG.msgtype)
            if T.ALIGNED_DEPTH_PNG in written:  # the recording's PNG, as it is
                depth = codec.decode(written[T.ALIGNED_DEPTH_PNG].data, T.ALIGNED_DEPTH_PNG.msgtype)
                depth_bytes, depth_format = bytes(depth.data), wirecompression.DEPTH_PNG_FORMAT
            elif self.wire_depth == "zstd":  # less than half PNG's cost to encode here and to decode in the tracker
                depth_bytes, depth_format = imagecodec.depth_zstd(d.array), wirecompression.DEPTH_ZSTD_FORMAT
            else:
                depth_bytes, depth_format = imagecodec.depth_png(d.array).tobytes(), wirecompression.DEPTH_PNG_FORMAT
            self._rgbd.put(rgbdmsgs.encoded_rgbd_msg(EncodedRgbd(
                c.frame_number, c.stamp_ns, bytes(colour.data), colour.format, depth_bytes, depth_format,
                self._device.depth_scale_m, self._device.color, self._frame)))

    def _behind(self, stamp_ns: int) -> bool:
        """Whether the tracker has `window` frames without a status, the oldest of them more than the
        lag older than this one (a burst within the lag it tracks in order: publish)."""
        if not self.window:
            return False
        waiting = self._rgbd.count - self.answered
        while len(self._unanswered) > max(waiting, 0):
            self._unanswered.popleft()
        if waiting < self.window:
            return False
        return not self._lag_ns or not self._unanswered or stamp_ns - self._unanswered[0] > self._lag_ns

    def end(self) -> None:
        """Tell consumers how many RGB-D frames went out (the tracker's end-of-stream), then stay
        until the tracker has taken them: a live tracker may be far behind, and a producer gone
        before its consumer reached the end would be taken for a dead one. Not until the tracker has
        finished: the camera closes, and its recording with it, while the map is completed."""
        self._rgbd_end.put(streammsgs.stream_end_msg(self._rgbd.topic.name, self._rgbd.count))
        self._bus.linger("tracker", taken=T.FRAMES_TAKEN)


class VizLogger:
    """Logs what is recorded to Rerun: colour, depth (aligned and raw), IMU; calibration once."""

    def __init__(self, viz: Any, device: DeviceDescription) -> None:
        self._viz = viz
        self._device = device
        self._static = False

    def __call__(self, cap: Capture, msgs: list[Encoded]) -> None:
        viz, d = self._viz, self._device
        if not self._static:
            if d.color is not None:
                viz.camera(T.COLOR.name.rsplit("/", 1)[0], d.color)
            self._static = True
        for v in cap.video():
            viz.set_time(v.stamp_ns, v.frame_number)
            if v.stream == "color":
                viz.rgb(T.COLOR.name, v.array)
            else:
                viz.depth((T.ALIGNED_DEPTH if v.stream == "aligned_depth" else T.DEPTH).name, v.array,
                          d.depth_scale_m)
        for m in cap.motion:
            viz.set_time(m.stamp_ns)
            base = (T.GYRO if m.stream == "gyro" else T.ACCEL).name
            for axis, value in zip("xyz", m.xyz, strict=True):
                viz.scalar(f"{base}/{axis}", value)
