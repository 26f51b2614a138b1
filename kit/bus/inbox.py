"""A stage's inbox: one bounded queue of what it receives, data and requests in arrival order.

Bounded, and filled with blocking puts from Zenoh's receive thread: a slow consumer slows its
producers, nothing is dropped. A plain Zenoh callback subscriber would queue without bound.

Locking: the queue's own. `closing` (an Event, set by `close`) releases a put blocked on a full
inbox once the bus closes; `last_put` is written by whichever thread delivers and only read as a
hint (is the bus idle?).
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Any

from octolog.schemas import codec
from octolog.schemas.topics import Topic


@dataclass(frozen=True)
class Received:
    """One sample taken from the inbox: its topic and raw CDR payload."""

    topic: Topic
    payload: bytes
    query: Any = None  # set for requests taken by `accept`: answer with `reply`
    source: bytes = b""  # the publisher's id if it numbers its samples (wire.describe_publisher)
    msg: Any = None  # the decoded message, once the bus has screened the sample

    def reply(self, msg: Any, topic: Topic) -> None:
        """Answer the request this is with `msg`, encoded as `topic`'s type."""
        self.query.reply(self.query.key_expr, codec.encode(msg, topic.msgtype))

    def decode(self) -> Any:
        return self.msg if self.msg is not None else codec.decode(self.payload, self.topic.msgtype)


class Inbox:
    """The bounded queue a stage's loop takes its samples from."""

    def __init__(self, size: int) -> None:
        self._queue: queue.Queue[Received] = queue.Queue(maxsize=size)
        self.closing = threading.Event()
        self.last_put = time.monotonic()  # when something last went in

    def put(self, item: Received) -> None:
        """Into the inbox, blocking (back-pressure); gives up only when the bus closes."""
        while not self.closing.is_set():
            try:
                self._queue.put(item, timeout=0.5)
                self.last_put = time.monotonic()
                return
            except queue.Full:
                continue

    def close(self) -> None:
        """Release puts blocked on a full inbox, and refuse further ones (the bus is closing)."""
        self.closing.set()

    def put_request(self, item: Received) -> None:
        """A request into the inbox, waiting for room however long it takes."""
        self._queue.put(item)

    def get(self, timeout_s: float) -> Received | None:
        """The next item, or None after `timeout_s`."""
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def get_nowait(self) -> Received | None:
        """The next item if one is waiting, else None."""
        try:
            return self._queue.get_nowait()
        except queue.Empty:
            return None

    def empty(self) -> bool:
        return self._queue.empty()
