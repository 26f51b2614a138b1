"""A stage's inbox: one bounded queue of what it receives, data and requests in arrival order.

Bounded, and filled with blocking puts from Zenoh's receive thread: a slow consumer slows its
producers, nothing is dropped. A plain Zenoh callback subscriber would queue without bound.

Locking: one Condition over the queue. `closing` (an Event, set by `close`) releases a put
blocked on a full inbox once the bus closes; `last_put` is written by whichever thread delivers and
only read as a hint (is the bus idle?).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from octolog.kit.bus.session import Query
from octolog.schemas import codec
from octolog.schemas.topics import Topic


@dataclass(frozen=True)
class Received:
    """One sample taken from the inbox: its topic and raw CDR payload."""

    topic: Topic
    payload: bytes
    query: Query | None = None  # set for requests taken by `accept`: answer with `reply`
    source: bytes = b""  # the publisher's id if it numbers its samples (wire.describe_publisher)
    msg: Any = None  # the decoded message, once the bus has screened the sample (its class is the topic's)

    def reply(self, msg: object, topic: Topic) -> None:
        """Answer the request this is with `msg`, encoded as `topic`'s type."""
        assert self.query is not None, "only a request taken by `accept` has someone to answer"
        self.query.reply(self.query.key_expr, codec.encode(msg, topic.msgtype))

    def decode(self) -> Any:  # Any: the class of `topic.msgtype`, known at run time
        return self.msg if self.msg is not None else codec.decode(self.payload, self.topic.msgtype)


class Inbox:
    """The bounded queue a stage's loop takes its samples from.

    A topic marked `keep_latest` is a progress signal, not data: a sample of it that arrives while
    the inbox's last item is one of the same topic replaces that one (in place, keeping the order
    with the other topics), so such samples never fill the inbox nor block their sender."""

    def __init__(self, size: int) -> None:
        """`size`: items it holds before a put waits; 0: unbounded (a put never waits, for a stage whose
        consumer keeps everything it takes anyway, so waiting would only block the transport)."""
        self._items: deque[Received] = deque()
        self._size = size if size > 0 else float("inf")
        self._cond = threading.Condition(threading.Lock())
        self._latest: set[Topic] = set()
        self.closing = threading.Event()
        self.last_put = time.monotonic()  # when something last went in

    def keep_latest(self, topic: Topic) -> None:
        """Samples of `topic` in a row collapse to the newest (see the class)."""
        with self._cond:
            self._latest.add(topic)

    def put(self, item: Received) -> None:
        """Into the inbox, blocking (back-pressure); gives up only when the bus closes."""
        with self._cond:
            while not self._replaces_last(item):
                if self.closing.is_set():
                    return
                if len(self._items) < self._size:
                    self._items.append(item)
                    break
                self._cond.wait(0.5)
            self.last_put = time.monotonic()
            self._cond.notify_all()

    def _replaces_last(self, item: Received) -> bool:
        if item.topic in self._latest and self._items and self._items[-1].topic == item.topic \
                and self._items[-1].query is None:
            self._items[-1] = item
            return True
        return False

    def close(self) -> None:
        """Release puts blocked on a full inbox, and refuse further ones (the bus is closing)."""
        self.closing.set()
        with self._cond:
            self._cond.notify_all()

    def put_request(self, item: Received) -> None:
        """A request into the inbox, waiting for room however long it takes."""
        with self._cond:
            self._cond.wait_for(lambda: len(self._items) < self._size)
            self._items.append(item)
            self._cond.notify_all()

    def get(self, timeout_s: float) -> Received | None:
        """The next item, or None after `timeout_s`."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._items, timeout_s):
                return None
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def get_nowait(self) -> Received | None:
        """The next item if one is waiting, else None."""
        return self.get(0.0)

    def empty(self) -> bool:
        with self._cond:
            return not self._items
