"""Publishing with numbered history: what lets a subscriber recover what a cut link lost.

With history on (`BusConfig.history` > 0) every publisher numbers its samples (an attachment, see
`wire`), keeps a bounded history of them and serves it on `<key>/@history/<publisher id>`. A
late or restarted subscriber gets a publisher's history from its oldest kept sample (for
keyframes: the whole run).

Locks, each guarding one thing and never held while taking another except in the order given:
- `Numbering.lock` (one per bus): numbering a sample and reading the other publishers' counts
  for its dependencies is one step, so the dependencies say exactly what was sent before it.
- `History._lock` (one per publisher): its samples, shared by the publishing thread and the
  threads answering history queries. Taken inside `Numbering.lock`, never the other way round.
"""

from __future__ import annotations

import threading
import uuid
from collections import deque

from octolog.kit.bus import wire
from octolog.kit.bus.ros2 import LATCHED, Ros2Mirror, Ros2Node, is_ros_type
from octolog.kit.bus.session import Query, Session, ZenohPublisher
from octolog.kit.busconfig import BusConfig
from octolog.schemas import codec
from octolog.schemas.topics import Topic

HISTORY_MB = 64  # byte cap of an ordinary publisher's history, on top of `history` samples


def keeps_all(topic: Topic) -> bool:
    """Streams a consumer must be able to rebuild from the start (a restarted mapper re-integrates
    every keyframe): their publishers keep everything, up to `BusConfig.keep_mb`. End messages are
    tiny and tell a late joiner how much to expect."""
    return topic.name.startswith("tracker/keyframe") or topic.name.endswith("/end")


class History:
    """A publisher's most recent samples by sequence number, bounded by count and bytes (the newest
    sample always stays)."""

    def __init__(self, max_samples: int | None, max_bytes: int) -> None:
        self.max_samples, self.max_bytes = max_samples, max_bytes
        self._items: deque[tuple[int, bytes, bytes]] = deque()  # seq, payload, attachment
        self._bytes = 0
        self._lock = threading.Lock()

    def add(self, seq: int, data: bytes, attachment: bytes) -> None:
        with self._lock:
            self._items.append((seq, data, attachment))
            self._bytes += len(data)
            while len(self._items) > 1 and (self._bytes > self.max_bytes or (
                    self.max_samples is not None and len(self._items) > self.max_samples)):
                self._bytes -= len(self._items.popleft()[1])

    def since(self, first: int, limit: int) -> tuple[int, list[tuple[int, bytes, bytes]]]:
        """The oldest kept seq, and up to `limit` samples from `first` on."""
        with self._lock:
            if not self._items:
                return 0, []
            oldest = self._items[0][0]
            start = max(0, first - oldest)
            return oldest, [self._items[i] for i in range(start, min(len(self._items), start + limit))]


class Numbering:
    """The numbered publishers of one bus: one lock numbers their samples one at a time."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.publishers: list[Publisher] = []


class Publisher:
    """A reliable, blocking publisher of one topic; with a history, numbers what it sends and
    keeps it."""

    def __init__(self, pub: ZenohPublisher, topic: Topic, history: History | None = None, source: bytes = b"",
                 key_crc: int = 0, numbering: Numbering | None = None, ros2: Ros2Mirror | None = None) -> None:
        self._pub = pub
        self._ros2 = ros2  # the same samples on rmw_zenoh's key (`BusConfig.ros2_domain`)
        self.topic = topic
        self.count = 0  # samples sent (with history: the seq of the next one)
        self._history, self._source, self._crc, self._numbering = history, source, key_crc, numbering

    def put(self, msg: object) -> bytes:
        """Encode `msg` as the topic's type and send it; the CDR bytes sent."""
        data = codec.encode(msg, self.topic.msgtype)
        self.put_raw(data)
        return data

    def put_raw(self, data: bytes) -> None:
        """Send CDR bytes as they are (blocks while the link is congested)."""
        if self._history is None:
            self._pub.put(data)
            self.count += 1
        else:
            self._pub.put(data, attachment=self._number(data))
        if self._ros2 is not None:
            self._ros2.put(data)

    def _number(self, data: bytes) -> bytes:
        """Give the sample its seq and dependencies and keep it (before it is sent: a subscriber
        that sees a gap can always fetch what preceded); the attachment to send it with."""
        assert self._history is not None and self._numbering is not None
        with self._numbering.lock:
            deps = [wire.dependency(p._source, p._crc, p.count) for p in self._numbering.publishers
                    if p is not self and p.count]
            att = wire.numbered_attachment(self.count, self._source, deps)
            self._history.add(self.count, data, att)
            self.count += 1
        return att


class Publishing:
    """Declares one bus's publishers; with history on, numbers them together and serves each one's
    history to subscribers that ask."""

    def __init__(self, session: Session, cfg: BusConfig, stage: str = "") -> None:
        self._session, self._cfg, self._stage = session, cfg, stage
        self._numbering = Numbering()
        self._ros2_node: Ros2Node | None = None

    def _ros2(self, topic: Topic) -> Ros2Mirror | None:
        """The rmw_zenoh mirror of a publisher of `topic`, when ROS 2 is asked for and the type is ROS's."""
        if self._cfg.ros2_domain < 0 or not is_ros_type(topic.msgtype):
            return None
        if self._ros2_node is None:
            self._ros2_node = Ros2Node(self._session, self._cfg.ros2_domain, self._stage)
        return self._ros2_node.mirror(topic.ros_name(self._cfg.namespace), topic.msgtype, uuid.uuid4().bytes,
                                      latched=topic.name in LATCHED)

    def publisher(self, topic: Topic) -> Publisher:
        key = topic.key(self._cfg.namespace)
        pub = self._session.declare_publisher(key)
        ros2 = self._ros2(topic)
        if not self._cfg.history:
            return Publisher(pub, topic, ros2=ros2)
        if keeps_all(topic):
            history = History(None, self._cfg.keep_mb << 20)
        else:
            history = History(self._cfg.history, HISTORY_MB << 20)
        # identifies this publisher (not the output: never written); its stage's name, for messages
        source = wire.publisher_id(self._stage, uuid.uuid4().bytes)
        hkey = wire.history_key(key, source)
        publisher = Publisher(pub, topic, history, source, wire.key_crc(key), self._numbering, ros2)

        def on_query(query: Query) -> None:
            # samples F.. (before U) of this publisher, or F.. if the query names no publisher
            wanted = wire.requested_range(query.parameters, source)
            if wanted is None:
                return
            first_seq, end_seq = wanted
            oldest, items = history.since(first_seq, wire.BATCH)
            for i, (seq, data, att) in enumerate(items):
                if i and end_seq is not None and seq >= end_seq:
                    break  # the first always goes: its `oldest` tells a loss from a delay
                query.reply(hkey, data, attachment=wire.history_attachment(oldest, att))

        # indirect: answering (possibly large, blocking) runs off Zenoh's receive thread
        self._session.declare_queryable(hkey, on_query, indirect=True)
        with self._numbering.lock:
            self._numbering.publishers.append(publisher)
        return publisher
