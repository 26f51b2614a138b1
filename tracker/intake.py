"""The tracker's intake: frames taken off the bus and prepared as they arrive, on helper threads.

A reader thread takes every sample off the bus in order. Each frame goes straight to the decode
thread, which decodes it and extracts its features (`Tracker.prepare`, a pure function of the
pixels; OpenCV releases the GIL) while the tracking thread works on an earlier one. So the second
core prepares frame N+1 while frame N is tracked, whether the frames come in lockstep from a replay
or live from a camera. Outputs do not depend on it: what is prepared is what `track` would compute.

Live, the tracking thread tracks the frames in order while the newest one waiting is at most
`lag_ms` of sensor time ahead of the next (a burst: the camera's or the bus's jitter, a slow
keyframe); further behind, it takes the newest and skips the older ones. A frame's preparation is
cancelled, if it has not started, once a frame more than `lag_ms` newer arrives (it would be skipped).
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor

from octolog.kit.bus import Bus, Received
from octolog.kit.cpuclock import charge
from octolog.kit.errors import InputError
from octolog.kit.geometry import RgbdFrame
from octolog.kit.imu import ImuSamples
from octolog.kit.viz import encode_jpeg
from octolog.schemas import codec, rgbdmsgs
from octolog.schemas.msgtypes import CompressedRgbdFrameMsg, RgbdFrameMsg
from octolog.schemas.topics import RGBD, RGBD_COMPRESSED, RGBD_END
from octolog.tracker.imu_intake import ImuIntake
from octolog.tracker.interface import Tracker

# a frame's message, its frame (or why it is none) and what `Tracker.prepare` made of it
Decoded = tuple[RgbdFrameMsg | CompressedRgbdFrameMsg, RgbdFrame | InputError, object]
FRAME_PRODUCERS = ("replay", "recorder")  # whichever sends the frames: a replay, or a recorder publishing live


def decode(r: Received, odometry: Tracker | None = None, viz: bool = False) -> Decoded:
    """A frame message, its decoded frame (or the InputError that says why it cannot be one) and,
    given the tracker, what `odometry.prepare` makes of it ahead of `track`; with `viz`, the frame's
    colour as the JPEG the recording logs (`extra["jpeg"]`), unless it came as one."""
    with charge("decode"):
        msg = r.decode()
        try:
            frame = rgbdmsgs.rgbd_from_msg(msg)
        except InputError as exc:
            return msg, exc, None
    colour = frame.extra.get("wire", (None,))[0]
    if viz and (colour is None or "jpeg" not in colour.format):
        frame.extra["jpeg"] = encode_jpeg(frame.rgb)
    if odometry is None:
        return msg, frame, None
    with charge("features"):
        return msg, frame, odometry.prepare(frame)


def is_frame(r: Received) -> bool:
    return r.topic in (RGBD, RGBD_COMPRESSED)


def _stamp(r: Received) -> int:
    return codec.stamp_ns(r.decode().header)


class Intake:
    """Samples off `bus` in order, frames with their preparation under way. Use as a context manager."""

    def __init__(self, bus: Bus, odometry: Tracker, *, viz: bool, live: bool, lag_ms: float = 0.0,
                 size: int = 8) -> None:
        self.bus, self.odometry, self.viz, self.live = bus, odometry, viz, live
        self._lag_ns = round(lag_ms * 1e6)
        self._q: queue.Queue[tuple[Received, Future | None] | BaseException] = queue.Queue(maxsize=size)
        self._held: list[tuple[Received, Future | None]] = []  # taken off the queue, not yet handed out
        self._decoder = ThreadPoolExecutor(1, thread_name_prefix="decode")
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, name="intake", daemon=True)
        self.imu = ImuIntake()  # the IMU's samples, each frame marked with how many came before it
        self._imu_marks: dict[int, tuple[int, int]] = {}  # id(frame sample) -> its mark

    def __enter__(self) -> Intake:
        self._reader.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        while self._reader.is_alive():  # it may be blocked on a full queue: make room
            self._drain()
            self._reader.join(timeout=0.05)
        self._decoder.shutdown(wait=True, cancel_futures=True)

    def _drain(self) -> None:
        try:
            while True:
                self._q.get_nowait()
        except queue.Empty:
            pass

    def _read(self) -> None:
        preparing: deque[tuple[int, Future]] = deque()  # live: (stamp, preparation) of recent frames
        try:
            while not self._stop.is_set():
                r = self.bus.receive()
                if r is None or self.imu.offer(r):
                    continue
                if is_frame(r):
                    self._imu_marks[id(r)] = self.imu.mark()
                if r.topic == RGBD_END:  # the stream is all off the bus: its source may leave now
                    for producer in FRAME_PRODUCERS:
                        self.bus.unwatch(producer)
                fut = self._decoder.submit(decode, r, self.odometry, self.viz) if is_frame(r) else None
                self._put((r, fut))
                if fut is not None and self.live:
                    stamp = _stamp(r)
                    while preparing and (preparing[0][1].done() or stamp - preparing[0][0] > self._lag_ns):
                        preparing.popleft()[1].cancel()  # if not started: this newer frame wins over it
                    preparing.append((stamp, fut))
        except BaseException as exc:  # noqa: BLE001 - the tracking thread raises it
            self._put(exc)

    def _put(self, item: tuple[Received, Future | None] | BaseException) -> None:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _take(self, timeout_s: float | None) -> tuple[Received, Future | None] | None:
        if self._held:
            return self._held.pop(0)
        try:
            item = self._q.get(timeout=timeout_s) if timeout_s is not None else self._q.get_nowait()
        except queue.Empty:
            return None
        if isinstance(item, BaseException):
            raise item
        return item

    def get(self, timeout_s: float = 0.25) -> tuple[Received, Future | None] | None:
        """The next sample and, for a frame, its preparation; None after `timeout_s`."""
        return self._take(timeout_s)

    def behind(self, r: Received, times: float = 1.0) -> bool:
        """Live: whether two or more frames wait and the newest is more than `times` the lag newer
        than frame `r` (one waiting frame is the next in line however far its stamp: a camera that
        dropped frames leaves a gap, not a backlog); the samples waiting stay in line."""
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, BaseException):
                self._q.put(item)  # raised in its turn, after what came before it
                break
            self._held.append(item)
        stamps = [_stamp(it[0]) for it in self._held if is_frame(it[0])]
        return len(stamps) >= 2 and max(stamps) - _stamp(r) > self._lag_ns * times

    def newer_frame(self) -> tuple[Received, Future | None] | None:
        """Live: the next sample if it is a frame already waiting (then the one before it is to be
        skipped), else None; a sample that is not a frame stays first in line."""
        item = self._take(None)
        if item is None or is_frame(item[0]):
            return item
        self._held.insert(0, item)
        return None

    def imu_before(self, r: Received) -> tuple[ImuSamples, tuple[int, int]]:
        """The IMU samples that came before frame `r` and were not taken yet, and how many of each
        stream have been taken by then (the status's record of them)."""
        mark = self._imu_marks.pop(id(r), None)
        return (self.imu.take(mark), mark) if mark is not None else (ImuSamples.empty(), (0, 0))

    def skip(self, r: Received) -> None:
        """Frame `r` is skipped: its IMU samples go with the next frame taken."""
        self._imu_marks.pop(id(r), None)

    def prepared(self, r: Received, fut: Future | None) -> Decoded:
        """The frame's decoding and preparation, waiting for it (or doing it here if it was cancelled)."""
        if fut is not None:
            try:
                return fut.result()
            except CancelledError:
                pass
        return decode(r, self.odometry, self.viz)
