"""A live consumer of what the recorder writes (Zenoh publishing, Rerun logging) on a thread of its own."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

from octolog.recorder.capture import Capture
from octolog.recorder.recording_types import Encoded, Sink


class LiveSink:
    """A consumer of written frames on its own thread (Zenoh publishing, Rerun logging), behind a
    small bounded queue: a slow consumer loses frames here, counted, and never stalls the file."""

    def __init__(self, name: str, fn: Sink, *, size: int, on_close: Callable[[], None] | None = None) -> None:
        self.name = name
        self.fn = fn
        self._on_close = on_close
        self._q: queue.Queue[tuple[Capture, list[Encoded]] | None] = queue.Queue(maxsize=size)
        self.dropped: dict[str, int] = {}
        self.error: Exception | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"recorder-{name}", daemon=True)
        self._thread.start()

    def offer(self, cap: Capture, msgs: list[Encoded]) -> None:
        if self.error is not None:
            return
        try:
            self._q.put_nowait((cap, msgs))
        except queue.Full:
            for s in cap.streams():
                self.dropped[s] = self.dropped.get(s, 0) + 1

    def _run(self) -> None:
        while (job := self._q.get()) is not None:
            if self.error is None:
                try:
                    self.fn(*job)
                except Exception as exc:  # noqa: BLE001 - reported by the recorder, file goes on
                    self.error = exc

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._q.put(None)
        self._thread.join()
        if self._on_close is not None and self.error is None:
            try:
                self._on_close()
            except Exception as exc:  # noqa: BLE001
                self.error = exc

