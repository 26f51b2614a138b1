"""In-order delivery and gap repair: each publisher's samples exactly once and in order.

A subscriber delivers each publisher's numbered samples exactly once and in order, and the topics
of one producing stage in the order they were sent (`wire`: dependencies). On a gap, when idle,
and when a lost peer is back it asks the publishers' histories for what it has not got, holding
later samples until the gap is filled. Samples without our numbering (history off, or from a ROS
bridge) go to the inbox as they arrive.

Locks (taken in this order, never the reverse):
- `_deliver`: one thread at a time moves samples to the inbox (Zenoh's receive thread for live
  samples, the recovery thread for history replies), so each stream leaves in order.
- `_state` (a Condition): the streams, the keys due for a history query and the recovery thread;
  it wakes the recovery thread. Never held while putting into the inbox, which may block.
- the loss callback's own lock (`Membership`), taken inside `_state` to report a loss.
`_closing` (an Event) stops the recovery thread.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from octolog.kit.bus import wire
from octolog.kit.bus.inbox import Inbox, Received
from octolog.kit.bus.session import Session
from octolog.kit.busconfig import BusConfig
from octolog.kit.errors import StageError
from octolog.schemas.topics import Topic

PROBE_S = 1.0  # an idle subscriber, or one with an open gap, asks the histories this often
QUERY_TIMEOUT_S = 10.0


@dataclass
class _Stream:
    """What a subscriber knows about one publisher of one key."""

    topic: Topic
    source: bytes  # the publisher's id
    nxt: int = 0  # the next seq to deliver
    # arrived, waiting for a gap to fill or a dependency: seq -> (payload, dependencies)
    held: dict[int, tuple[bytes, tuple[wire.Dependency, ...]]] = field(default_factory=dict)
    started: bool = False  # something was delivered: a missing seq from now on is a loss
    wanted: int = 0  # another stream's sample depends on this one's samples before `wanted`
    held_bytes: int = 0  # the payload bytes in `held`
    refused: bool = False  # it went over the held bound: its samples are dropped from now on

    def gap(self) -> bool:
        return self.nxt < self.wanted or (bool(self.held) and self.nxt not in self.held)


class InOrderDelivery:
    """Takes one bus's subscriptions into its inbox, in order, repairing gaps from the histories."""

    def __init__(self, session: Session, cfg: BusConfig, stage: str, inbox: Inbox,
                 on_loss: Callable[[str], None], on_fatal: Callable[[str], None]) -> None:
        self._session, self._cfg, self._stage, self._inbox = session, cfg, stage, inbox
        self._on_loss = on_loss  # samples gone for good (older than the publisher's history)
        self._on_fatal = on_fatal  # a publisher went over the held bound
        self._held_bytes = 0  # payload bytes held behind gaps, over every stream (`max_held_mb`)
        # recovery (history > 0): per key, per publisher id, the delivery state
        self._streams: dict[str, dict[bytes, _Stream]] = {}
        self._recovered: dict[str, Topic] = {}  # key -> topic, for every subscribed key
        self._crcs: dict[int, str] = {}  # crc32 of a subscribed key -> the key
        self._state = threading.Condition(threading.Lock())
        self._due: set[str] = set()  # keys to ask the histories about now
        self._deliver = threading.Lock()
        self._closing = threading.Event()
        self._recovery: threading.Thread | None = None
        self._ends: dict[str, float] = {}  # topic -> when its end message showed a shortfall
        self.recovered = 0  # samples that came from a history rather than live

    def subscribe(self, topics: Iterable[Topic]) -> None:
        """Feed these topics into the inbox: per publisher exactly once and in order (with
        history), as they arrive across topics."""
        for topic in topics:
            key = topic.key(self._cfg.namespace)

            def on_sample(data: bytes, att: bytes | None, topic: Topic = topic, key: str = key) -> None:
                # Blocking put in Zenoh's receive thread: back-pressure, never a drop.
                if not self._cfg.history or att is None:
                    self._inbox.put(Received(topic, data))
                    return
                numbered = wire.parse_numbered(att)
                if numbered is None:  # someone else's attachment (a ROS bridge): no numbering
                    self._inbox.put(Received(topic, data))
                    return
                self._offer(key, numbered, data, None)
                self._flush()

            if self._cfg.history:
                with self._state:
                    self._recovered[key] = topic
                    self._crcs[wire.key_crc(key)] = key
                    self._streams.setdefault(key, {})
            self._session.subscribe(key, on_sample)
            if self._cfg.history:
                self._request(key)  # a late joiner: what the publishers already sent

    @property
    def held_bytes(self) -> int:
        """Payload bytes held behind gaps, over every stream."""
        with self._state:
            return self._held_bytes

    def catch_up(self) -> None:
        """Ask every history now (a lost peer is back: what it sent meanwhile may be missing)."""
        if self._recovered:
            self._request()

    def close(self) -> None:
        """Stop the recovery thread (waits for a query in flight to time out)."""
        self._closing.set()
        with self._state:
            self._state.notify_all()
        if self._recovery is not None:
            self._recovery.join(timeout=QUERY_TIMEOUT_S + 1)
            self._recovery = None

    def expect_count(self, topic: Topic, received: int, announced: int) -> None:
        """After a stream's end message: a shortfall is a loss once recovery had time to fill it.

        Without recovery (history 0) the end message travels behind all the data, so a shortfall at
        that moment is final; with it, missed samples can arrive after the end message. Call this at
        the end message and whenever the inbox is idle until the counts match.
        """
        if received >= announced:
            return
        since = self._ends.setdefault(topic.name, time.monotonic())
        if not self._cfg.history or time.monotonic() - since > self._cfg.peer_timeout_s:
            raise StageError(f"{self._stage}: {announced - received} of {announced} messages on "
                             f"{topic.key(self._cfg.namespace)} never arrived (link closed or producer restarted)")

    # --- holding and delivering (under `_state`, then `_deliver`) ---------------------------------

    def _stream(self, key: str, source: bytes) -> _Stream:
        streams = self._streams[key]
        if source not in streams:
            streams[source] = _Stream(self._recovered[key], source)
        return streams[source]

    def _offer(self, key: str, numbered: wire.Numbered, data: bytes, oldest: int | None) -> None:
        """Take one numbered sample (live, or from a history reply with the oldest seq kept there)."""
        seq = numbered.seq
        with self._state:
            st = self._stream(key, numbered.source)
            if oldest is not None and st.nxt < oldest:
                # the publisher no longer keeps what we lack: for a late joiner that is the past it
                # never asked for; once a stream has started it is a loss
                if st.started:
                    self._on_loss(f"{oldest - st.nxt} samples on {key}")
                for s in [s for s in st.held if s < oldest]:
                    self._unhold(st, s)
                st.nxt = oldest
            if st.refused or seq < st.nxt or seq in st.held:
                return  # a duplicate (live and recovered, or recovered twice), or a refused publisher's
            gap_was_open = st.gap()
            st.held[seq] = (data, numbered.deps)
            st.held_bytes += len(data)
            self._held_bytes += len(data)
            self.recovered += oldest is not None
            if self._held_bytes > self._cfg.max_held_mb << 20:
                self._refuse(key)
            if st.gap() and not gap_was_open:
                # a new gap before this one: ask for it now (an open one is asked every PROBE_S)
                self._due.add(key)
                self._state.notify_all()

    def _ready(self) -> tuple[_Stream, bytes] | None:
        """A sample that may go now: next in its stream, everything it depends on delivered."""
        for streams in self._streams.values():
            for st in streams.values():
                if st.nxt not in st.held:
                    continue
                data, deps = st.held[st.nxt]
                waiting = False
                for source, crc, count in deps:
                    dkey = self._crcs.get(crc)
                    if dkey is None:
                        continue  # a topic this stage does not take
                    dep = self._stream(dkey, source)
                    if dep.nxt < count:
                        waiting = True
                        if count > dep.wanted:
                            new = not dep.gap()
                            dep.wanted = count
                            if new:
                                self._due.add(dkey)
                                self._state.notify_all()
                if not waiting:
                    self._unhold(st, st.nxt)
                    st.nxt += 1
                    st.started = True
                    return st, data
        return None

    def _unhold(self, st: _Stream, seq: int) -> None:
        data, _ = st.held.pop(seq)
        st.held_bytes -= len(data)
        self._held_bytes -= len(data)

    def _refuse(self, key: str) -> None:
        """Over the held bound: the stream holding the most behind its gap is refused from now on,
        its held samples freed, and the stage told (it ends with this one line)."""
        worst_key, st = max(((k, st) for k, streams in self._streams.items() for st in streams.values()),
                            key=lambda ks: ks[1].held_bytes)
        n, mb = len(st.held), st.held_bytes / 2**20
        for seq in list(st.held):
            self._unhold(st, seq)
        st.refused = True
        self._on_fatal(f"{self._stage}: {wire.describe_publisher(st.source)} on {worst_key} left a gap at sample "
                       f"{st.nxt} that its history never filled: the {n} later samples held ({mb:.1f} MB) reached "
                       f"the bound (bus max_held_mb = {self._cfg.max_held_mb}); its samples are refused")

    def _flush(self) -> None:
        """Deliver whatever may go, in order; `_deliver` keeps two threads from interleaving."""
        with self._deliver:
            while True:
                with self._state:
                    ready = self._ready()
                if ready is None:
                    return
                self._inbox.put(Received(ready[0].topic, ready[1], source=ready[0].source))

    # --- asking the histories (the recovery thread) ------------------------------------------------

    def _request(self, key: str | None = None) -> None:
        """Ask the histories about `key` (or every subscribed key) soon, from the recovery thread."""
        with self._state:
            self._due |= {key} if key else set(self._recovered)
            self._state.notify_all()
            if self._recovery is None and not self._closing.is_set():
                self._recovery = threading.Thread(target=self._recover_loop, name=f"{self._stage}-recovery",
                                                  daemon=True)
                self._recovery.start()

    def _recover_loop(self) -> None:
        while not self._closing.is_set():
            with self._state:
                if not self._due:
                    self._state.wait(PROBE_S)
                due = set(self._due)
                self._due.clear()
                # every PROBE_S: keys with an open gap, and all keys when nothing came for a while
                # (samples lost at the end of a stream leave no gap behind them)
                idle = self._inbox.empty() and time.monotonic() - self._inbox.last_put > PROBE_S
                for key, streams in self._streams.items():
                    if idle or any(st.gap() for st in streams.values()):
                        due.add(key)
            for key in sorted(due):
                if self._closing.is_set():
                    return
                self._query(key)

    def _query(self, key: str) -> None:
        with self._state:
            # per known publisher: from the next seq, up to the first one held (just the gap)
            wants = [(src, st.nxt, min(st.held) if st.held else (st.wanted if st.wanted > st.nxt else None))
                     for src, st in self._streams[key].items()]
        selector = wire.history_selector(key, wants)
        got: dict[bytes, int] = {}
        try:
            for data, raw in self._session.get(selector, QUERY_TIMEOUT_S):
                reply = wire.parse_history_reply(raw)
                if reply is None:
                    continue
                oldest, numbered = reply
                got[numbered.source] = got.get(numbered.source, 0) + 1
                self._offer(key, numbered, data, oldest)
        except Exception:  # the session is closing, or the network is gone: the next probe retries
            if self._closing.is_set():
                return
        self._flush()
        if any(n >= wire.BATCH for n in got.values()):  # there may be more
            with self._state:
                self._due.add(key)
