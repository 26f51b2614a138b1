"""The Zenoh transport: the only module that imports zenoh.

Pipeline topics are reliable with congestion control BLOCK; subscribers feed one bounded inbox per
stage, so a slow consumer slows its producers and nothing is dropped. Stages announce themselves
with liveliness tokens: a producer waits until its consumers are ready, and every stage notices
when a peer stage disappears (process died, link cut) instead of waiting forever.

Loss-free across link failures and restarts (docs/architecture.md, "Bus"): every publisher numbers
its samples (an attachment: sequence number and publisher id), keeps a bounded history of them and
serves it on `<key>/@history/<publisher id>`. A subscriber delivers each publisher's samples exactly
once and in order, and the topics of one producing stage in the order they were sent; on a gap,
when idle, and when a lost peer is back it asks the history for what it has not got, holding later
samples until the gap is filled. A late or restarted subscriber gets
a publisher's history from its oldest kept sample (for keyframes: the whole run).
"""

from __future__ import annotations

import json
import os
import queue
import re
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from octolog.kit.errors import BusError, StageError
from octolog.schemas import codec
from octolog.schemas.topics import Topic, stage_token

_BLOCK_CLOSE = "transport/link/tx/queue/congestion_control/block/wait_before_close"
_ZENOH_DEFAULT_BLOCK_CLOSE_US = 5_000_000
CONNECT_TIMEOUT_MS = 30_000
BLOCK_CLOSE_US = 600_000_000  # a consumer stalled for 10 minutes is dead, not slow

# Sequence numbers ride in the sample's attachment: seq (u64 LE), publisher id (16 bytes), and the
# sample's dependencies: for each other numbered publisher of the same session that had sent
# something, its id, crc32 of its key and its count then. A subscriber delivers a sample only after
# everything it depends on among the keys it takes, so topics of one session keep their order (a
# pose correction never overtakes the keyframes it corrects). History replies prepend the oldest seq
# the publisher still keeps, so a subscriber can tell late from lost.
_HEAD = struct.Struct("<Q16sH")
_DEP = struct.Struct("<16sIQ")
_OLDEST = struct.Struct("<Q")
HISTORY = "@history"  # a verbatim chunk: `**` subscribers and queries never match it by accident
HISTORY_MB = 64  # byte cap of an ordinary publisher's history, on top of `history` samples
PROBE_S = 1.0  # an idle subscriber, or one with an open gap, asks the histories this often
QUERY_TIMEOUT_S = 10.0
WAKE_S = 0.2  # a thread blocked on an event wakes this often, so signal handlers run (wait_interruptibly)
BATCH = 16  # samples per history reply: a large backlog comes in several queries
DONE = "_octolog/done"  # `<ns>/_octolog/done/<stage>`: put by a stage that finished without error


def _parse(raw: bytes) -> tuple[int, bytes, tuple[tuple[bytes, int, int], ...]] | None:
    """seq, publisher id, dependencies of a numbered attachment; None if it is not one of ours."""
    if len(raw) < _HEAD.size:
        return None
    seq, source, n = _HEAD.unpack_from(raw)
    if len(raw) != _HEAD.size + n * _DEP.size:
        return None
    return seq, source, tuple(_DEP.unpack_from(raw, _HEAD.size + i * _DEP.size) for i in range(n))


def keeps_all(topic: Topic) -> bool:
    """Streams a consumer must be able to rebuild from the start (a restarted mapper re-integrates
    every keyframe): their publishers keep everything, up to `BusConfig.keep_mb`. End messages are
    tiny and tell a late joiner how much to expect."""
    return topic.name.startswith("tracker/keyframe") or topic.name.endswith("/end")


@dataclass(frozen=True)
class BusConfig:
    """Transport settings shared by every stage (see `octolog <cmd> --help`)."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    namespace: str = ""
    zenoh_config: str | None = None
    multicast_scouting: bool = True
    # samples each publisher keeps (at most HISTORY_MB of them) so that subscribers can recover
    # what a cut link lost and late joiners get the recent past; 0: plain pub/sub, no recovery
    history: int = 32
    # the streams that `keeps_all` (keyframes) keep every sample up to this many MB per publisher
    keep_mb: int = 2048
    # how long a vanished peer stage may stay away (a cut link) before it counts as dead
    peer_timeout_s: float = 30.0

    def validate(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise BusError(f"--mode {self.mode!r}: want peer, client or router")
        if self.history < 0 or self.keep_mb < 0 or self.peer_timeout_s <= 0:
            raise BusError("bus history and keep_mb must be >= 0 and peer_timeout_s > 0")


def zenoh_config(cfg: BusConfig) -> Any:
    import zenoh

    try:
        zc = zenoh.Config.from_file(cfg.zenoh_config) if cfg.zenoh_config else zenoh.Config()
        zc.insert_json5("mode", json.dumps(cfg.mode))
        if cfg.connect:
            zc.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
            # a client gives up at once by default; stages may start before their router
            if json.loads(zc.get_json("connect/timeout_ms")) is None:
                zc.insert_json5("connect/timeout_ms", str(CONNECT_TIMEOUT_MS))
        if cfg.listen:
            zc.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
        if not cfg.multicast_scouting:
            zc.insert_json5("scouting/multicast/enabled", "false")
        # Zenoh closes a link whose BLOCK queue stays full for 5 s, losing what was queued: a
        # mapper busy with a keyframe would lose data. Back-pressure must wait, so wait longer.
        if json.loads(zc.get_json(_BLOCK_CLOSE)) == _ZENOH_DEFAULT_BLOCK_CLOSE_US:
            zc.insert_json5(_BLOCK_CLOSE, str(BLOCK_CLOSE_US))
    except Exception as exc:  # zenoh raises ZError with the parser's message, over several lines
        where = f" {cfg.zenoh_config}" if cfg.zenoh_config else ""
        raise BusError(f"invalid Zenoh configuration{where}: {_one_line(exc)}") from None
    return zc


def _one_line(exc: BaseException) -> str:
    """Zenoh's multi-line parser messages as one line: position and reason, no source paths."""
    lines = [ln.strip(" |=") for ln in str(exc).splitlines()]
    text = " ".join(ln for ln in lines if ln and ln != "^---")
    return re.sub(r" at /\S+\.rs:\d+\.?", "", text).strip()


@dataclass(frozen=True)
class Received:
    """One sample taken from the inbox: its topic and raw CDR payload."""

    topic: Topic
    payload: bytes
    query: Any = None  # set for requests taken by `accept`: answer with `reply`

    def reply(self, msg: Any, topic: Topic) -> None:
        self.query.reply(self.query.key_expr, codec.encode(msg, topic.msgtype))

    def decode(self) -> Any:
        return codec.decode(self.payload, self.topic.msgtype)


class _History:
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


class _Session:
    """The numbered publishers of one Bus: one lock orders their numbering."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.publishers: list[Publisher] = []


class Publisher:
    """A reliable, blocking publisher of one topic; numbers what it sends and keeps a history."""

    def __init__(self, pub: Any, topic: Topic, history: _History | None = None, source: bytes = b"",
                 key_crc: int = 0, session: _Session | None = None) -> None:
        self._pub = pub
        self.topic = topic
        self.count = 0
        self._history, self._source, self._crc, self._session = history, source, key_crc, session

    def put(self, msg: Any) -> bytes:
        data = codec.encode(msg, self.topic.msgtype)
        self.put_raw(data)
        return data

    def put_raw(self, data: bytes) -> None:
        if self._history is None:
            self._pub.put(data)
            self.count += 1
            return
        self._pub.put(data, attachment=self._number(data))

    def _number(self, data: bytes) -> bytes:
        """Give the sample its seq and dependencies and keep it (before it is sent: a subscriber
        that sees a gap can always fetch what preceded); the attachment to send it with."""
        assert self._history is not None and self._session is not None
        with self._session.lock:
            deps = [_DEP.pack(p._source, p._crc, p.count) for p in self._session.publishers
                    if p is not self and p.count]
            att = _HEAD.pack(self.count, self._source, len(deps)) + b"".join(deps)
            self._history.add(self.count, data, att)
            self.count += 1
        return att


@dataclass
class _Stream:
    """What a subscriber knows about one publisher of one key."""

    topic: Topic
    nxt: int = 0  # the next seq to deliver
    # arrived, waiting for a gap to fill or a dependency: seq -> (payload, dependencies)
    held: dict[int, tuple[bytes, tuple[tuple[bytes, int, int], ...]]] = field(default_factory=dict)
    started: bool = False  # something was delivered: a missing seq from now on is a loss
    wanted: int = 0  # another stream's sample depends on this one's samples before `wanted`

    def gap(self) -> bool:
        return self.nxt < self.wanted or (bool(self.held) and self.nxt not in self.held)


class Bus:
    """One Zenoh session for one stage. Use as a context manager."""

    def __init__(self, cfg: BusConfig, stage: str, *, inbox_size: int = 8) -> None:
        self.cfg = cfg
        self.stage = stage
        self.namespace = cfg.namespace
        self._inbox: queue.Queue[Received] = queue.Queue(maxsize=inbox_size)
        self._session: Any = None
        self._keep: list[Any] = []
        self._alive: set[str] = set()
        self._lost: dict[str, float] = {}  # stage -> monotonic time it vanished
        self._missed: list[str] = []  # samples gone for good (older than the publisher's history)
        self._ends: dict[str, float] = {}  # topic -> when its end message showed a shortfall
        self._watched: set[str] = set()
        self._followed: set[str] = set()  # tracked like watched ones, but their absence is no error
        self._alive_changed = threading.Condition()
        # recovery (history > 0): per key, per publisher id, the delivery state
        self._streams: dict[str, dict[bytes, _Stream]] = {}
        self._recovered: dict[str, Topic] = {}  # key -> topic, for every subscribed key
        self._crcs: dict[int, str] = {}  # crc32 of a subscribed key -> the key
        self._numbered = _Session()
        self._state = threading.Condition(threading.Lock())  # guards _streams, _due; wakes the recovery thread
        self._due: set[str] = set()  # keys to ask the histories about now
        self._deliver = threading.Lock()  # one deliverer at a time keeps each stream in order
        self._last_put = time.monotonic()
        self._closing = threading.Event()
        self._recovery: threading.Thread | None = None
        self.recovered = 0  # samples that came from a history rather than live
        self._announced = False
        self._done: set[str] = set()  # followed stages that said they finished

    # --- lifecycle -------------------------------------------------------------------------

    def __enter__(self) -> Bus:
        import zenoh

        if os.environ.get("RUST_LOG"):  # Zenoh's own log (link open/close, lease expiry) on demand
            zenoh.try_init_log_from_env()
        zc = zenoh_config(self.cfg)  # a BusError of its own for a bad configuration
        try:
            self._session = zenoh.open(zc)
        except Exception as exc:
            raise BusError(f"cannot open Zenoh session ({self.cfg.mode}): {_one_line(exc)}") from None
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None and self._announced and self._session is not None:
            # finished, not crashed: producers lingering for this stage may go (see `linger`)
            import zenoh

            self._session.put(self._key(f"{DONE}/{self.stage}"), b"",
                              congestion_control=zenoh.CongestionControl.BLOCK)
        self.close()

    def _key(self, key: str) -> str:
        ns = self.namespace.strip("/")
        return f"{ns}/{key}" if ns else key

    def close(self) -> None:
        self._closing.set()
        with self._state:
            self._state.notify_all()
        if self._recovery is not None:
            self._recovery.join(timeout=QUERY_TIMEOUT_S + 1)
            self._recovery = None
        if self._session is not None:
            self._keep.clear()
            try:
                self._session.close()
            finally:
                self._session = None

    @property
    def session(self) -> Any:
        if self._session is None:
            raise BusError("bus is not open")
        return self._session

    # --- data ------------------------------------------------------------------------------

    def publisher(self, topic: Topic) -> Publisher:
        import uuid

        import zenoh

        key = topic.key(self.namespace)
        pub = self.session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        self._keep.append(pub)
        if not self.cfg.history:
            return Publisher(pub, topic)
        if keeps_all(topic):
            history = _History(None, self.cfg.keep_mb << 20)
        else:
            history = _History(self.cfg.history, HISTORY_MB << 20)
        source = uuid.uuid4().bytes  # identifies this publisher (not the output: never written)
        hkey = f"{key}/{HISTORY}/{source.hex()}"
        publisher = Publisher(pub, topic, history, source, zlib.crc32(key.encode()), self._numbered)

        def on_query(query: Any) -> None:
            # `?from=F;<id>=F[:U]`: samples F.. (before U) of this publisher, or F.. for any
            params = query.parameters
            first, _, until = (params.get(source.hex()) or params.get("from") or "0").partition(":")
            try:
                first_seq, end_seq = int(first), int(until) if until else None
            except ValueError:
                return
            oldest, items = history.since(first_seq, BATCH)
            for i, (seq, data, att) in enumerate(items):
                if i and end_seq is not None and seq >= end_seq:
                    break  # the first always goes: its `oldest` tells a loss from a delay
                query.reply(hkey, data, attachment=_OLDEST.pack(oldest) + att)

        # indirect: answering (possibly large, blocking) runs off Zenoh's receive thread
        self._keep.append(self.session.declare_queryable(hkey, zenoh.handlers.Callback(on_query)))
        with self._numbered.lock:
            self._numbered.publishers.append(publisher)
        return publisher

    def subscribe(self, topics: Iterable[Topic]) -> None:
        """Feed these topics into this stage's bounded inbox: per publisher exactly once and in
        order (with history), as they arrive across topics."""
        import zenoh

        for topic in topics:
            key = topic.key(self.namespace)

            def on_sample(sample: Any, topic: Topic = topic, key: str = key) -> None:
                # Blocking put in Zenoh's receive thread: back-pressure, never a drop.
                att = sample.attachment
                data = sample.payload.to_bytes()
                if not self.cfg.history or att is None:
                    self._put(Received(topic, data))
                    return
                numbered = _parse(att.to_bytes())
                if numbered is None:  # someone else's attachment (a ROS bridge): no numbering
                    self._put(Received(topic, data))
                    return
                seq, source, deps = numbered
                self._offer(key, source, seq, data, deps, None)
                self._flush()

            if self.cfg.history:
                with self._state:
                    self._recovered[key] = topic
                    self._crcs[zlib.crc32(key.encode())] = key
                    self._streams.setdefault(key, {})
            handler = zenoh.handlers.Callback(on_sample, indirect=False)
            self._keep.append(self.session.declare_subscriber(key, handler))
            if self.cfg.history:
                self._request(key)  # a late joiner: what the publishers already sent

    # --- recovery ----------------------------------------------------------------------------

    def _put(self, item: Received) -> None:
        """Into the inbox, blocking (back-pressure); gives up only when the bus closes."""
        while not self._closing.is_set():
            try:
                self._inbox.put(item, timeout=0.5)
                self._last_put = time.monotonic()
                return
            except queue.Full:
                continue

    def _stream(self, key: str, source: bytes) -> _Stream:
        streams = self._streams[key]
        if source not in streams:
            streams[source] = _Stream(self._recovered[key])
        return streams[source]

    def _offer(self, key: str, source: bytes, seq: int, data: bytes, deps: tuple[tuple[bytes, int, int], ...],
               oldest: int | None) -> None:
        """Take one numbered sample (live, or from a history reply with the oldest seq kept there)."""
        with self._state:
            st = self._stream(key, source)
            if oldest is not None and st.nxt < oldest:
                # the publisher no longer keeps what we lack: for a late joiner that is the past it
                # never asked for; once a stream has started it is a loss
                if st.started:
                    self._missed.append(f"{oldest - st.nxt} samples on {key}")
                for s in [s for s in st.held if s < oldest]:
                    del st.held[s]
                st.nxt = oldest
            if seq < st.nxt or seq in st.held:
                return  # a duplicate (live and recovered, or recovered twice)
            gap_was_open = st.gap()
            st.held[seq] = (data, deps)
            self.recovered += oldest is not None
            if st.gap() and not gap_was_open:
                # a new gap before this one: ask for it now (an open one is asked every PROBE_S)
                self._due.add(key)
                self._state.notify_all()

    def _ready(self) -> tuple[_Stream, bytes] | None:
        """A sample that may go now: next in its stream, everything it depends on delivered."""
        for key, streams in self._streams.items():
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
                    del st.held[st.nxt]
                    st.nxt += 1
                    st.started = True
                    return st, data
        return None

    def _flush(self) -> None:
        """Deliver whatever may go, in order; the lock keeps two threads from interleaving."""
        with self._deliver:
            while True:
                with self._state:
                    ready = self._ready()
                if ready is None:
                    return
                self._put(Received(ready[0].topic, ready[1]))

    def _request(self, key: str | None = None) -> None:
        """Ask the histories about `key` (or every subscribed key) soon, from the recovery thread."""
        with self._state:
            self._due |= {key} if key else set(self._recovered)
            self._state.notify_all()
            if self._recovery is None and not self._closing.is_set():
                self._recovery = threading.Thread(target=self._recover_loop, name=f"{self.stage}-recovery",
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
                idle = self._inbox.empty() and time.monotonic() - self._last_put > PROBE_S
                for key, streams in self._streams.items():
                    if idle or any(st.gap() for st in streams.values()):
                        due.add(key)
            for key in sorted(due):
                if self._closing.is_set():
                    return
                self._query(key)

    def _query(self, key: str) -> None:
        import zenoh

        with self._state:
            # per known publisher: from the next seq, up to the first one held (just the gap)
            parts = []
            for src, st in self._streams[key].items():
                until = min(st.held) if st.held else (st.wanted if st.wanted > st.nxt else None)
                parts.append(f"{src.hex()}={st.nxt}" + (f":{until}" if until is not None else ""))
        selector = f"{key}/{HISTORY}/*?from=0" + "".join(f";{p}" for p in parts)
        got: dict[bytes, int] = {}
        try:
            for reply in self.session.get(selector, consolidation=zenoh.ConsolidationMode.NONE,
                                          timeout=QUERY_TIMEOUT_S):
                ok = reply.ok
                raw = ok.attachment.to_bytes() if ok is not None and ok.attachment is not None else b""
                numbered = _parse(raw[_OLDEST.size:]) if len(raw) > _OLDEST.size else None
                if numbered is None:
                    continue
                seq, source, deps = numbered
                got[source] = got.get(source, 0) + 1
                self._offer(key, source, seq, ok.payload.to_bytes(), deps, _OLDEST.unpack_from(raw)[0])
        except Exception:  # the session is closing, or the network is gone: the next probe retries
            if self._closing.is_set():
                return
        self._flush()
        if any(n >= BATCH for n in got.values()):  # there may be more
            with self._state:
                self._due.add(key)

    def receive(self, timeout_s: float = 0.25) -> Received | None:
        """The next sample, or None after `timeout_s`; raises StageError if a watched peer died."""
        try:
            return self._inbox.get(timeout=timeout_s)
        except queue.Empty:
            self.check_peers()
            return None

    def serve(self, topic: Topic, latest: Callable[[], bytes | None]) -> None:
        """Answer `get` on this topic's key with `latest()` (CDR bytes), e.g. the current map."""
        import zenoh

        key = topic.key(self.namespace)

        def on_query(query: Any) -> None:
            data = latest()
            if data is not None:
                query.reply(key, data)

        q = self.session.declare_queryable(key, zenoh.handlers.Callback(on_query, indirect=False))
        self._keep.append(q)

    def accept(self, topic: Topic) -> None:
        """Take queries on this topic's key into the inbox, in order with the data, to be answered
        by the stage's own loop (e.g. "save the map now")."""
        import zenoh

        def on_query(query: Any) -> None:
            self._inbox.put(Received(topic, b"", query))

        q = self.session.declare_queryable(topic.key(self.namespace), zenoh.handlers.Callback(on_query, indirect=False))
        self._keep.append(q)

    def fetch(self, topic: Topic, timeout_s: float = 10.0) -> Any | None:
        """`get` a topic from its queryable; the decoded reply, or None if nobody answered.

        A session that has just opened may not know the queryable yet (declarations arrive
        after the link): a plain `get` then returns at once with nothing. So wait, up to the
        timeout, until a matching queryable is known, then ask.
        """
        deadline = time.monotonic() + timeout_s
        querier = self.session.declare_querier(topic.key(self.namespace), timeout=timeout_s)
        listener = None
        try:
            known = threading.Event()
            listener = querier.declare_matching_listener(lambda status: known.set() if status.matching else None)
            if querier.matching_status.matching:
                known.set()
            if not known.wait(max(0.0, deadline - time.monotonic())):
                return None
            for reply in querier.get():
                if reply.ok is not None:
                    return codec.decode(reply.ok.payload.to_bytes(), topic.msgtype)
            return None
        finally:
            if listener is not None:
                listener.undeclare()
            querier.undeclare()

    def receive_nowait(self) -> Received | None:
        """The next sample if one is waiting, else None."""
        try:
            return self._inbox.get_nowait()
        except queue.Empty:
            return None

    # --- stages: readiness and liveness ------------------------------------------------------

    def start(self, topics: Iterable[Topic], *, wait_for: Iterable[str] = (), timeout_s: float = 60.0) -> None:
        """The usual stage start: subscribe, wait for the stages named, then announce readiness."""
        self.subscribe(topics)
        wait_for = tuple(wait_for)
        self.watch(wait_for)
        self.wait_for(wait_for, timeout_s)
        self.announce()

    def announce(self) -> None:
        """Declare this stage ready (call after subscribing)."""
        token = self.session.liveliness().declare_token(stage_token(self.stage, self.namespace))
        self._keep.append(token)
        self._announced = True

    def watch(self, stages: Iterable[str], *, required: bool = True) -> None:
        """Track the liveliness of peer stages; `check_peers` raises once a required one has been
        gone for `peer_timeout_s`. A peer that comes back makes the subscribers catch up at once."""
        import zenoh

        stages = set(stages)
        if required:
            self._watched |= stages
        else:
            self._followed |= stages
            done_prefix = self._key(f"{DONE}/")

            def on_done(sample: Any) -> None:
                with self._alive_changed:
                    self._done.add(str(sample.key_expr)[len(done_prefix):])
                    self._alive_changed.notify_all()

            self._keep.append(self.session.declare_subscriber(
                self._key(f"{DONE}/*"), zenoh.handlers.Callback(on_done, indirect=False)))
        prefix = stage_token("", self.namespace)

        def on_token(sample: Any) -> None:
            name = str(sample.key_expr)[len(prefix):]
            if name not in self._watched and name not in self._followed:
                return
            back = False
            with self._alive_changed:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._alive.add(name)
                    back = self._lost.pop(name, None) is not None  # back after a cut or a restart
                else:
                    self._alive.discard(name)
                    self._lost.setdefault(name, time.monotonic())
                self._alive_changed.notify_all()
            if back and self._recovered:
                self._request()

        sub = self.session.liveliness().declare_subscriber(
            stage_token("*", self.namespace), zenoh.handlers.Callback(on_token, indirect=False), history=True
        )
        self._keep.append(sub)

    def wait_for(self, stages: Iterable[str], timeout_s: float = 30.0) -> None:
        """Block until every named stage has announced itself (they must be watched)."""
        stages = set(stages)
        deadline = time.monotonic() + timeout_s
        with self._alive_changed:
            while not stages <= self._alive:
                self._raise_if_lost()
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = ", ".join(sorted(stages - self._alive))
                    raise StageError(f"{self.stage}: no {missing} stage appeared within {timeout_s:.0f} s "
                                     f"(namespace {self.namespace or '(none)'!r}; are the stages connected?)")
                self._alive_changed.wait(min(left, 0.5))

    def unwatch(self, stage: str) -> None:
        """Stop caring about a peer (it finished its stream and may leave)."""
        with self._alive_changed:
            self._watched.discard(stage)
            if stage not in self._followed:
                self._lost.pop(stage, None)

    def linger(self, stage: str) -> bool:
        """Stay up, histories and all, until `stage` has finished, so that a consumer restarted
        meanwhile still recovers everything it needs. Follow the stage from the start
        (`watch([stage], required=False)`).

        Returns True once it said it finished; False at once if it never showed up, or once it has
        been gone for `peer_timeout_s` (dead for good: nothing left to wait for).
        """
        with self._alive_changed:
            while stage not in self._done:
                since = self._lost.get(stage)
                if stage not in self._alive and (since is None or time.monotonic() - since > self.cfg.peer_timeout_s):
                    return False
                self._alive_changed.wait(0.5)
            return True

    def expect_count(self, topic: Topic, received: int, announced: int) -> None:
        """After a stream's end message: a shortfall is a loss once recovery had time to fill it.

        Without recovery (history 0) the end message travels behind all the data, so a shortfall at
        that moment is final; with it, missed samples can arrive after the end message. Call this at
        the end message and whenever the inbox is idle until the counts match.
        """
        if received >= announced:
            return
        since = self._ends.setdefault(topic.name, time.monotonic())
        if not self.cfg.history or time.monotonic() - since > self.cfg.peer_timeout_s:
            raise StageError(f"{self.stage}: {announced - received} of {announced} messages on "
                             f"{topic.key(self.namespace)} never arrived (link closed or producer restarted)")

    def check_peers(self) -> None:
        with self._alive_changed:
            self._raise_if_lost()

    def _raise_if_lost(self) -> None:
        if self._missed:
            raise StageError(f"{self.stage}: {self._missed[0]} were lost for good (the outage outlasted what "
                             f"the publisher keeps in its history)")
        # A vanished producer may come back (a cut link) and, with liveliness and data on different
        # routes, one that sent its last message and left can be seen leaving before that message
        # lands. Only a long absence counts as death.
        now = time.monotonic()
        for stage, since in self._lost.items():
            if stage in self._watched and now - since > self.cfg.peer_timeout_s:
                raise StageError(f"{self.stage}: the {stage} stage disappeared for {self.cfg.peer_timeout_s:g} s "
                                 f"(process died or link cut)")


def serve_router(listen: tuple[str, ...], *, zenoh_config: str | None = None,
                 stop: threading.Event | None = None, ready: Callable[[], None] | None = None) -> None:
    """Host a Zenoh router in this process until `stop` is set (or forever); `ready()` is called
    once its session is open."""
    cfg = BusConfig(mode="router", listen=listen, zenoh_config=zenoh_config, multicast_scouting=False)
    stop = stop or threading.Event()
    with Bus(cfg, "router"):
        if ready is not None:
            ready()
        wait_interruptibly(stop)


def wait_interruptibly(event: threading.Event) -> None:
    """Block until `event` is set, in slices: a SIGTERM or Ctrl-C may be delivered to one of
    Zenoh's threads, and Python runs its handler (KeyboardInterrupt, see octolog.cli) only when the
    main thread next runs bytecode, which an untimed wait never does."""
    while not event.wait(WAKE_S):
        pass
