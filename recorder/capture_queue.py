"""The bounded queue from the capture thread to the recorder's writer thread, and the per-stream
accounting of every frame that does not reach the file (recorder/recording_types.py: StreamStats).

Nothing is dropped silently: frame-number gaps at the device, aligned depth without a colour
partner, captures the queue had no room for and captures left unwritten after a write failure are
each counted per stream.
"""

from __future__ import annotations

import queue
import threading
from typing import Any

from octolog.recorder.capture import Capture
from octolog.recorder.recording_types import STREAMS, StreamStats

MOTION_BATCH = 64  # IMU samples per queue entry without a frame: the queue counts frames, not IMU samples


class CaptureQueue:
    """Captures waiting for the writer, at most `size` of them, and the per-stream counts.

    `submit` never blocks a real-time source: when the queue is full the capture is dropped and
    counted (`queue_drops`). With `block_when_full` (a source that can wait) it waits instead. Once
    `fail` is called, nothing more is accepted: what comes is counted `unwritten`.
    """

    def __init__(self, size: int, *, block_when_full: bool) -> None:
        self._q: queue.Queue[Capture | None] = queue.Queue(maxsize=size)  # None: the end
        self._block = block_when_full
        self._motion_batch: list[Any] = []
        self.stats = {s: StreamStats() for s in STREAMS}
        self.failed = threading.Event()  # the writer cannot go on; the capture side should stop
        self.ended = False  # the writer side has taken the end marker

    # --- capture side ----------------------------------------------------------------------

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

    def end(self) -> None:
        """Queue the IMU samples still batched, then the end marker (waits for room)."""
        if self._motion_batch:
            self._put(Capture(motion=self._motion_batch))
            self._motion_batch = []
        self._q.put(None)

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
            self.count(cap, "unwritten")
            return
        if self._block:
            while not self.failed.is_set():
                try:
                    self._q.put(cap, timeout=0.1)
                    return
                except queue.Full:
                    continue
            self.count(cap, "unwritten")
            return
        try:
            self._q.put_nowait(cap)
        except queue.Full:
            self.count(cap, "queue_drops")

    # --- writer side -----------------------------------------------------------------------

    def take(self, timeout: float) -> Capture | None:
        """The next Capture, or None when none came within `timeout` or the end marker came
        (then `ended` is set)."""
        try:
            cap = self._q.get(timeout=timeout)
        except queue.Empty:
            return None
        if cap is None:
            self.ended = True
        return cap

    def empty(self) -> bool:
        return self._q.empty()

    def qsize(self) -> int:
        return self._q.qsize()

    def fail(self) -> None:
        """Accept nothing more: what is submitted from now on is counted unwritten."""
        self.failed.set()

    def drain_unwritten(self) -> None:
        """Take what is queued now without waiting, counting each Capture unwritten (and noting
        the end marker)."""
        while True:
            try:
                cap = self._q.get_nowait()
            except queue.Empty:
                return
            if cap is None:
                self.ended = True
            else:
                self.count(cap, "unwritten")

    def count(self, cap: Capture, what: str) -> None:
        """Add one to counter `what` (a StreamStats field) of each stream sample in `cap`."""
        for s in cap.streams():
            setattr(self.stats[s], what, getattr(self.stats[s], what) + 1)
