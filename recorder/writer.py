"""The recording core: captures from the capture thread to MCAP files on a writer thread, handed to
the live sinks (recorder/livesink.py) as they are written, with a status line and a result
(recorder/recording_types.py).

`Recorder` composes parts that own their state: the bounded queue and its per-stream drop counts
(recorder/capture_queue.py: CaptureQueue), the encoding of a capture into messages, on a thread
pool (recorder/capture_encoding.py: encode_capture), and the output files, split by size or sensor
time, with the free-space checks (recorder/split_output.py: SplitMcapOutput).

Nothing is dropped silently. Per stream it counts frame-number gaps at the device, frames the
writer could not keep up with (the queue was full), aligned depth that had no colour partner,
frames a live sink (bus, Rerun) had no room for, and frames left unwritten after a write
failure. The counts are in the status line, in the result, and in each file's `recording`
metadata record.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from octolog.kit.errors import RecorderError, WriteFailed
from octolog.recorder.capture import Capture, DeviceDescription, blank_capture
from octolog.recorder.capture_encoding import encode_capture, tf_static
from octolog.recorder.capture_queue import CaptureQueue
from octolog.recorder.livesink import LiveSink
from octolog.recorder.recording_types import (
    STREAMS,
    Encoded,
    RecorderStatus,
    RecordResult,
    WriterParams,
    camera_transforms,
    frame_names,
)
from octolog.recorder.split_output import RecordingProgress, SplitMcapOutput
from octolog.schemas import codec


class Recorder:
    """Takes Captures from the capture thread and writes them on its own threads.

    `submit` never blocks a real-time source: when the queue is full the capture is dropped and
    counted. With `block_when_full` (a source that can wait, like the software device on demand)
    it waits instead, so nothing is lost however slow the disk.
    """

    def __init__(self, part: Callable[[int], Path], device: DeviceDescription, params: WriterParams, *,
                 config_json: str, sinks: Sequence[LiveSink] = ()) -> None:
        self.device = device
        self.frames = frame_names(params.frame_prefix)
        self._encoding = params.encoding
        self._threads = params.encode_threads
        self._sinks = list(sinks)
        self._queue = CaptureQueue(params.queue_size, block_when_full=params.block_when_full)
        self._pool = ThreadPoolExecutor(max_workers=params.encode_threads, thread_name_prefix="recorder-encode")
        self.stats = self._queue.stats
        self.failed = self._queue.failed  # the writer cannot go on; the capture side should stop
        self.result = RecordResult(streams=self.stats)
        self.error: RecorderError | None = None
        self._crash: Exception | None = None
        self._t0 = time.monotonic()
        self._last_status = (self._t0, {s: 0 for s in STREAMS}, 0)
        transforms = camera_transforms(device, self.frames)
        self._output = SplitMcapOutput(
            part, compression=params.compression, chunk_size=params.chunk_size_bytes,
            split_size=params.split_size_bytes, split_ns=params.split_duration_ns, min_free=params.min_free_bytes,
            metadata={**device.metadata(), "config": {"recorder": config_json}}, transforms=transforms,
            progress=self._progress)
        # the lazy set-up (type store, each type's CDR code and schema, the codecs) now, not on the first
        # frame: the camera is streaming by then, and a late first frame holds back the live ones behind it
        for m in [*self._encode(blank_capture(device)), tf_static(transforms, 0)]:
            codec.msgdef(m.topic.msgtype)
        self._thread = threading.Thread(target=self._write_loop, name="recorder-writer", daemon=True)
        self._thread.start()

    # --- capture side ------------------------------------------------------------------------

    def submit(self, cap: Capture) -> None:
        """Queue one Capture (recorder/capture_queue.py: CaptureQueue.submit)."""
        self._queue.submit(cap)

    def close(self, reason: str) -> RecordResult:
        """Write what is queued, finish the file(s) and stop the sinks. Raises RecorderError if
        writing failed (the message says what is on disk)."""
        self._queue.end()
        self._thread.join()
        self._pool.shutdown()
        for sink in self._sinks:
            sink.close()
            for s, n in sink.dropped.items():
                self.stats[s].live_drops += n
            self.result.held_back += getattr(sink.fn, "held_back", 0)
        self.result.stop_reason = self.error.args[0] if self.error else reason
        path = self._output.path
        finish_error = self._output.finish()
        self._sync_result()
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
        out = self._output
        total = out.bytes_written
        self._last_status = (now, frames, total)
        return RecorderStatus(
            elapsed_s=now - self._t0, frames=frames,
            rates_hz={s: (frames[s] - f_prev.get(s, 0)) / dt for s in frames},
            dropped={s: st.dropped for s, st in self.stats.items()},
            live_drops=sum(st.live_drops for st in self.stats.values())
            + sum(sum(k.dropped.values()) for k in self._sinks),
            messages=out.messages, flushed_messages=out.flushed_messages,
            mb_written=total / 1e6, mb_per_s=(total - b_prev) / dt / 1e6, free_mb=out.free_bytes / 1e6,
            queue=self._queue.qsize(), files=out.files,
            held_back=sum(getattr(k.fn, "held_back", 0) for k in self._sinks))

    def _progress(self) -> RecordingProgress:
        """What a finished file's `recording` record says about the recording as a whole."""
        r = self.result
        return RecordingProgress(stop_reason=r.stop_reason, streams=self.stats, dropped_total=r.dropped,
                                 last_stamp_ns=r.last_stamp_ns, wall_s=time.monotonic() - self._t0)

    def _sync_result(self) -> None:
        out, r = self._output, self.result
        if len(r.paths) != len(out.paths):
            r.paths = list(out.paths)
        r.messages, r.bytes = out.closed_messages, out.closed_bytes

    # --- writer thread -----------------------------------------------------------------------

    def _write_loop(self) -> None:
        q = self._queue
        pending: deque[tuple[Capture, Future[list[Encoded]]]] = deque()
        while not q.ended or pending:
            if not q.ended:
                cap = q.take(0.05 if pending else 0.5)
                if cap is not None:
                    pending.append((cap, self._pool.submit(self._encode, cap)))
            # write in order; keep at most `threads` encodes in flight, finish all at the end
            while pending and (pending[0][1].done() or len(pending) > self._threads or q.ended or q.empty()):
                cap, fut = pending.popleft()
                if self.failed.is_set():
                    q.count(cap, "unwritten")
                    continue
                try:
                    self._write(cap, fut.result())
                except RecorderError as exc:
                    self.error = exc
                    q.fail()
                    q.count(cap, "unwritten")
                    continue
                except Exception as exc:  # noqa: BLE001 - a bug: finish the file, then re-raise in close()
                    self._crash = exc
                    q.fail()
                    q.count(cap, "unwritten")
                    continue
                try:
                    self._output.check_disk()
                except RecorderError as exc:
                    self.error = exc
                    q.fail()
            if self.failed.is_set():  # count what is still queued, keep draining
                q.drain_unwritten()

    def _encode(self, cap: Capture) -> list[Encoded]:
        """CDR messages of one Capture (runs in the encode pool; cv2 releases the GIL)."""
        return encode_capture(cap, self.device, self.frames, self._encoding)

    def _write(self, cap: Capture, msgs: list[Encoded]) -> None:
        video = cap.color is not None or cap.depth is not None or cap.aligned_depth is not None
        try:
            self._output.write(msgs, cap.stamp_ns, may_split=video)
        finally:
            self._sync_result()
        self._queue.count(cap, "frames")
        r = self.result
        for m in msgs:
            r.first_stamp_ns = m.stamp_ns if r.first_stamp_ns == 0 else min(r.first_stamp_ns, m.stamp_ns)
            r.last_stamp_ns = max(r.last_stamp_ns, m.stamp_ns)
        for sink in self._sinks:
            sink.offer(cap, msgs)
