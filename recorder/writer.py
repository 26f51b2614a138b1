"""The recording core: a bounded queue from the capture thread to a writer thread, encoding,
MCAP files (split by size or sensor time), drop accounting, handing frames to the live sinks
(recorder/livesink.py) and the status (recorder/recording_types.py).

Nothing is dropped silently. Per stream it counts frame-number gaps at the device, frames the
writer could not keep up with (the queue was full), aligned depth that had no colour partner,
frames a live sink (bus, Rerun) had no room for, and frames left unwritten after a write
failure. The counts are in the status line, in the result, and in each file's `recording`
metadata record.
"""

from __future__ import annotations

import errno
import json
import queue
import shutil
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from octolog.kit.errors import DiskFull, McapError, RecorderError, WriteFailed
from octolog.kit.geometry import Intrinsics
from octolog.kit.mcaplog import McapWriter
from octolog.recorder.capture import Capture, DeviceDescription, blank_capture
from octolog.recorder.livesink import LiveSink
from octolog.recorder.recording_types import (
    JPEG_FORMAT,
    PNG_FORMAT,
    STREAMS,
    Encoded,
    RecorderStatus,
    RecordResult,
    StreamStats,
    WriterParams,
    camera_transforms,
    frame_names,
)
from octolog.schemas import codec, imagecodec, posemsgs, sensormsgs
from octolog.schemas import topics as T
from octolog.schemas.topics import Topic

MOTION_BATCH = 64  # IMU samples per queue entry without a frame: the queue counts frames, not IMU samples
DISK_CHECK_S = 0.5  # free-space checks at most this often (and after every chunk): statvfs is not free


class Recorder:
    """Takes Captures from the capture thread and writes them on its own threads.

    `submit` never blocks a real-time source: when the queue is full the capture is dropped and
    counted. With `block_when_full` (a source that can wait, like the software device on demand)
    it waits instead, so nothing is lost however slow the disk.
    """

    def __init__(self, part: Callable[[int], Path], device: DeviceDescription, params: WriterParams, *,
                 config_json: str, sinks: Sequence[LiveSink] = ()) -> None:
        self._part = part
        self.device = device
        self._config_json = config_json
        self._compression = params.compression
        self._chunk_size = params.chunk_size_bytes
        self._enc = params.encoding
        self._split_size = params.split_size_bytes
        self._split_ns = params.split_duration_ns
        self._block = params.block_when_full
        self._threads = params.encode_threads
        self._min_free = params.min_free_bytes
        self._sinks = list(sinks)
        self._q: queue.Queue[Capture | None] = queue.Queue(maxsize=params.queue_size)
        self._pool = ThreadPoolExecutor(max_workers=params.encode_threads, thread_name_prefix="recorder-encode")
        self.stats = {s: StreamStats() for s in STREAMS}
        self.result = RecordResult(streams=self.stats)
        self.error: RecorderError | None = None
        self._crash: Exception | None = None
        self.failed = threading.Event()  # the writer cannot go on; the capture side should stop
        self._writer: McapWriter | None = None
        self._file_index = -1
        self._file_first_ns = 0
        self._file_messages: dict[str, int] = {}
        self._closed_bytes = 0
        self._messages_before = 0
        self._motion_batch: list[Any] = []
        self._seen_batch: list[tuple[str, int]] = []
        self._t0 = time.monotonic()
        self._last_status = (self._t0, {s: 0 for s in STREAMS}, 0)
        self._next_disk_check = 0.0
        self._checked_bytes = 0
        self._free_bytes = self._disk_free()
        self.frames = frame_names(params.frame_prefix)
        self._color_info = device.color
        self._depth_info = device.depth
        # the lazy set-up (type store, each type's CDR code and schema, the codecs) now, not on the first
        # frame: the camera is streaming by then, and a late first frame holds back the live ones behind it
        tf = Encoded(T.TF_STATIC, codec.encode(posemsgs.tf_msg(self._transforms(), 0), T.TF_STATIC.msgtype), 0)
        for m in [*self._encode(blank_capture(device)), tf]:
            codec.msgdef(m.topic.msgtype)
        self._thread = threading.Thread(target=self._write_loop, name="recorder-writer", daemon=True)
        self._thread.start()

    # --- capture side ------------------------------------------------------------------------

    def submit(self, cap: Capture) -> None:
        """Queue one Capture. IMU-only captures are batched into the next frame's (or flushed at
        MOTION_BATCH samples) so the queue counts frames, not IMU samples."""
        self._account(cap)
        if cap.color is None and cap.depth is None and cap.aligned_depth is None:
            self._motion_batch += cap.motion
            if len(self._motion_batch) < MOTION_BATCH:
                return
            cap = Capture()
        if self._motion_batch:
            cap.motion = self._motion_batch + cap.motion
            self._motion_batch = []
        self._put(cap)

    def _account(self, cap: Capture) -> None:
        for stream, fn in cap.seen:
            st = self.stats[stream]
            if st.last_frame_number >= 0 and fn > st.last_frame_number + 1:
                st.device_gaps += fn - st.last_frame_number - 1
            st.last_frame_number = max(st.last_frame_number, fn)
        for stream in cap.unpaired:
            self.stats[stream].unpaired += 1

    def _put(self, cap: Capture) -> None:
        if self.failed.is_set():
            self._count(cap, "unwritten")
            return
        if self._block:
            while not self.failed.is_set():
                try:
                    self._q.put(cap, timeout=0.1)
                    return
                except queue.Full:
                    continue
            self._count(cap, "unwritten")
            return
        try:
            self._q.put_nowait(cap)
        except queue.Full:
            self._count(cap, "queue_drops")

    def _count(self, cap: Capture, what: str) -> None:
        for s in cap.streams():
            setattr(self.stats[s], what, getattr(self.stats[s], what) + 1)

    def close(self, reason: str) -> RecordResult:
        """Write what is queued, finish the file(s) and stop the sinks. Raises RecorderError if
        writing failed (the message says what is on disk)."""
        if self._motion_batch:
            self._put(Capture(motion=self._motion_batch))
            self._motion_batch = []
        self._q.put(None)
        self._thread.join()
        self._pool.shutdown()
        for sink in self._sinks:
            sink.close()
            for s, n in sink.dropped.items():
                self.stats[s].live_drops += n
            self.result.held_back += getattr(sink.fn, "held_back", 0)
        self.result.stop_reason = self.error.args[0] if self.error else reason
        path = self._writer.path if self._writer else None
        finish_error = self._close_file()
        self.result.wall_s = time.monotonic() - self._t0
        if isinstance(self.error, WriteFailed):  # say what is on disk, now that it is known
            tail = f"; {finish_error}" if finish_error else f"; {path} is finished with everything before that"
            raise type(self.error)(self.error.args[0] + tail)
        if self.error is not None:
            raise self.error
        if self._crash is not None:
            raise self._crash
        if finish_error is not None:
            raise finish_error
        return self.result

    @property
    def sink_errors(self) -> list[str]:
        return [f"{s.name}: {s.error}" for s in self._sinks if s.error is not None]

    # --- status ------------------------------------------------------------------------------

    def status(self) -> RecorderStatus:
        """Counters since the start, rates since the previous call."""
        now = time.monotonic()
        frames = {s: st.frames for s, st in self.stats.items()}
        t_prev, f_prev, b_prev = self._last_status
        dt = max(now - t_prev, 1e-6)
        total = self._bytes_written()
        self._last_status = (now, frames, total)
        w = self._writer
        return RecorderStatus(
            elapsed_s=now - self._t0, frames=frames,
            rates_hz={s: (frames[s] - f_prev.get(s, 0)) / dt for s in frames},
            dropped={s: st.dropped for s, st in self.stats.items()},
            live_drops=sum(st.live_drops for st in self.stats.values())
            + sum(sum(k.dropped.values()) for k in self._sinks),
            messages=self._messages_before + (w.count if w else 0),
            flushed_messages=self._messages_before + (w.flushed_count if w else 0),
            mb_written=total / 1e6, mb_per_s=(total - b_prev) / dt / 1e6, free_mb=self._free_bytes / 1e6,
            queue=self._q.qsize(), files=self._file_index + 1,
            held_back=sum(getattr(k.fn, "held_back", 0) for k in self._sinks))

    def _bytes_written(self) -> int:
        w = self._writer
        return self._closed_bytes + (w.size_bytes if w else 0)

    def _disk_free(self) -> int:
        try:
            return shutil.disk_usage(self._part(0).parent).free
        except OSError:
            return 0

    # --- writer thread -----------------------------------------------------------------------

    def _write_loop(self) -> None:
        pending: deque[tuple[Capture, Future[list[Encoded]]]] = deque()
        ended = False
        while not ended or pending:
            if not ended:
                try:
                    cap = self._q.get(timeout=0.05 if pending else 0.5)
                    if cap is None:
                        ended = True
                    else:
                        pending.append((cap, self._pool.submit(self._encode, cap)))
                except queue.Empty:
                    pass
            # write in order; keep at most `threads` encodes in flight, finish all at the end
            while pending and (pending[0][1].done() or len(pending) > self._threads or ended
                               or self._q.empty()):
                cap, fut = pending.popleft()
                if self.failed.is_set():
                    self._count(cap, "unwritten")
                    continue
                try:
                    self._write(cap, fut.result())
                except RecorderError as exc:
                    self.error = exc
                    self.failed.set()
                    self._count(cap, "unwritten")
                    continue
                except Exception as exc:  # noqa: BLE001 - a bug: finish the file, then re-raise in close()
                    self._crash = exc
                    self.failed.set()
                    self._count(cap, "unwritten")
                    continue
                try:
                    self._check_disk()
                except RecorderError as exc:
                    self.error = exc
                    self.failed.set()
            if self.failed.is_set():  # count what is still queued, keep draining
                while True:
                    try:
                        cap = self._q.get_nowait()
                    except queue.Empty:
                        break
                    if cap is None:
                        ended = True
                    else:
                        self._count(cap, "unwritten")

    def _encode(self, cap: Capture) -> list[Encoded]:
        """CDR messages of one Capture (runs in the encode pool; cv2 releases the GIL)."""
        out: list[Encoded] = []
        e = self._enc
        if cap.color is not None:
            c = cap.color
            if e.color_codec == "jpeg":
                ok, buf = cv2.imencode(".jpg", cv2.cvtColor(c.array, cv2.COLOR_RGB2BGR),
                                       [cv2.IMWRITE_JPEG_QUALITY, e.jpeg_quality])
                msg = sensormsgs.compressed_image_msg(buf.tobytes(), JPEG_FORMAT, c.stamp_ns, self.frames["color"])
                out.append(Encoded(T.COLOR_JPEG, codec.encode(msg, T.COLOR_JPEG.msgtype), c.stamp_ns))
            else:
                msg = sensormsgs.image_msg(c.array, c.stamp_ns, self.frames["color"])
                out.append(Encoded(T.COLOR, codec.encode(msg, T.COLOR.msgtype), c.stamp_ns))
            out.append(self._info(T.COLOR_INFO, self._color_info, c.stamp_ns, self.frames["color"]))
        for v, raw, png, info, intr, frame in (
                (cap.aligned_depth, T.ALIGNED_DEPTH, T.ALIGNED_DEPTH_PNG, T.ALIGNED_DEPTH_INFO, self._color_info,
                 self.frames["color"]),
                (cap.depth, T.DEPTH, T.DEPTH_PNG, T.DEPTH_INFO, self._depth_info, self.frames["depth"])):
            if v is None:
                continue
            if e.depth_codec == "png":
                msg = sensormsgs.compressed_image_msg(imagecodec.depth_png(v.array, e.png_level).tobytes(), PNG_FORMAT,
                                                 v.stamp_ns, frame)
                out.append(Encoded(png, codec.encode(msg, png.msgtype), v.stamp_ns))
            else:
                msg = sensormsgs.image_msg(v.array, v.stamp_ns, frame)
                out.append(Encoded(raw, codec.encode(msg, raw.msgtype), v.stamp_ns))
            out.append(self._info(info, intr, v.stamp_ns, frame))
        for m in cap.motion:
            topic = T.GYRO if m.stream == "gyro" else T.ACCEL
            kw = {"angular_velocity" if m.stream == "gyro" else "linear_acceleration": m.xyz}
            msg = sensormsgs.imu_msg(m.stamp_ns, self.frames[m.stream], **kw)
            out.append(Encoded(topic, codec.encode(msg, topic.msgtype), m.stamp_ns))
        return out

    @staticmethod
    def _info(topic: Topic, intr: Intrinsics | None, stamp: int, frame: str) -> Encoded:
        assert intr is not None
        return Encoded(topic, codec.encode(sensormsgs.camera_info_msg(intr, stamp, frame), topic.msgtype), stamp)

    def _write(self, cap: Capture, msgs: list[Encoded]) -> None:
        video = cap.color is not None or cap.depth is not None or cap.aligned_depth is not None
        if self._writer is None or (video and self._want_split(cap.stamp_ns)):
            self._rotate(cap.stamp_ns)
        w = self._writer
        assert w is not None
        try:
            for m in msgs:
                w.write(m.topic.name, m.topic.msgtype, m.data, log_time_ns=m.stamp_ns, publish_time_ns=m.stamp_ns)
                self._file_messages[m.topic.name] = self._file_messages.get(m.topic.name, 0) + 1
        except McapError as exc:
            raise self._write_failure(exc) from None
        for s in cap.streams():
            self.stats[s].frames += 1
        r = self.result
        for m in msgs:
            r.first_stamp_ns = m.stamp_ns if r.first_stamp_ns == 0 else min(r.first_stamp_ns, m.stamp_ns)
            r.last_stamp_ns = max(r.last_stamp_ns, m.stamp_ns)
        for sink in self._sinks:
            sink.offer(cap, msgs)

    def _check_disk(self) -> None:
        """Stop while there is room to finish the file, rather than at ENOSPC."""
        now = time.monotonic()
        written = self._bytes_written()
        if now >= self._next_disk_check or written - self._checked_bytes >= self._chunk_size:
            self._next_disk_check = now + DISK_CHECK_S
            self._checked_bytes = written
            self._free_bytes = self._disk_free()
            if self._min_free and self._free_bytes < self._min_free:
                raise RecorderError(f"disk nearly full ({self._free_bytes / 1e6:.0f} MB free, limit "
                                    f"{self._min_free / 1e6:.0f} MB): recording stopped; "
                                    f"{self._writer.path if self._writer else ''} is complete")

    def _write_failure(self, exc: McapError) -> WriteFailed:
        """The error for a failed write; close() completes its message once it is known whether the
        file could be finished. McapWriter raises McapError from the OSError, whose errno tells a
        full disk from other I/O errors."""
        cause = exc.__context__
        full = isinstance(cause, OSError) and cause.errno == errno.ENOSPC
        kind, what = (DiskFull, "disk full") if full else (WriteFailed, f"write failed ({exc})")
        return kind(f"{what}: recording stopped after {self.result.messages + self._writer_count()} messages")

    def _writer_count(self) -> int:
        return self._writer.count if self._writer else 0

    def _want_split(self, stamp_ns: int) -> bool:
        w = self._writer
        if w is None:
            return True
        if self._split_size and w.size_bytes >= self._split_size:
            return True
        return bool(self._split_ns and stamp_ns - self._file_first_ns >= self._split_ns)

    def _rotate(self, stamp_ns: int) -> None:
        err = self._close_file()
        if err is not None:
            raise err
        self._file_index += 1
        path = self._part(self._file_index)
        try:
            w = McapWriter(path, compression=self._compression, chunk_size=self._chunk_size)
            for name, data in self.device.metadata().items():
                w.add_metadata(name, data)
            w.add_metadata("config", {"recorder": self._config_json})
            self._writer = w
            self._file_first_ns = stamp_ns
            self._file_messages = {}
            self.result.paths.append(path)
            tf = posemsgs.tf_msg(self._transforms(), stamp_ns)
            w.write(T.TF_STATIC.name, T.TF_STATIC.msgtype, codec.encode(tf, T.TF_STATIC.msgtype),
                    log_time_ns=stamp_ns, publish_time_ns=stamp_ns)
            self._file_messages[T.TF_STATIC.name] = 1
        except McapError as exc:
            if self._writer is None:
                raise RecorderError(str(exc)) from None
            raise self._write_failure(exc) from None

    def _transforms(self) -> list[tuple[str, str, np.ndarray]]:
        return camera_transforms(self.device, self.frames)

    def _close_file(self) -> RecorderError | None:
        w = self._writer
        if w is None:
            return None
        self._writer = None
        meta = {"file_index": str(self._file_index), "stop_reason": self.result.stop_reason or "split",
                "messages": json.dumps(self._file_messages, sort_keys=True),
                "streams": json.dumps({s: {k: v for k, v in vars(st).items() if k != "last_frame_number"}
                                       for s, st in self.stats.items()}, sort_keys=True),
                "dropped_total": str(self.result.dropped),
                "first_stamp_ns": str(self._file_first_ns), "last_stamp_ns": str(self.result.last_stamp_ns),
                "wall_s": f"{time.monotonic() - self._t0:.3f}"}
        err: RecorderError | None = None
        try:
            w.add_metadata("recording", meta)
        except McapError:
            pass  # after a write failure the counts are in the error message and the result
        try:
            w.close()
        except McapError as exc:
            err = RecorderError(str(exc))
        self._messages_before += w.count
        self.result.messages += w.count
        self._closed_bytes += w.size_bytes
        self.result.bytes = self._closed_bytes
        return err
