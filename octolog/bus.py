"""The Zenoh transport: the only module that imports zenoh.

Pipeline topics are reliable with congestion control BLOCK; subscribers feed one bounded inbox per
stage, so a slow consumer slows its producers and nothing is dropped. Stages announce themselves
with liveliness tokens: a producer waits until its consumers are ready, and every stage notices
when a peer stage disappears (process died, link cut) instead of waiting forever.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from octolog.errors import BusError, StageError
from schemas import codec
from schemas.topics import Topic, stage_token


_BLOCK_CLOSE = "transport/link/tx/queue/congestion_control/block/wait_before_close"
_ZENOH_DEFAULT_BLOCK_CLOSE_US = 5_000_000
CONNECT_TIMEOUT_MS = 30_000
BLOCK_CLOSE_US = 600_000_000  # a consumer stalled for 10 minutes is dead, not slow


@dataclass(frozen=True)
class BusConfig:
    """Transport settings shared by every stage (see `octolog <cmd> --help`)."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    namespace: str = ""
    zenoh_config: str | None = None
    multicast_scouting: bool = True
    # samples each publisher keeps so that subscribers can recover what a cut link lost (Zenoh's
    # advanced publisher/subscriber); 0: plain pub/sub. Off by default: in the netns test a 6 s
    # `ip link down` still lost samples with it on (tests/test_distributed.py), and it caches
    # `history` frames per publisher
    history: int = 0
    # how long a vanished peer stage may stay away (a cut link) before it counts as dead
    peer_timeout_s: float = 30.0

    def validate(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise BusError(f"--mode {self.mode!r}: want peer, client or router")
        if self.history < 0 or self.peer_timeout_s <= 0:
            raise BusError("bus history must be >= 0 and peer_timeout_s > 0")


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
    except Exception as exc:  # zenoh raises ZError with the parser's message
        raise BusError(f"invalid Zenoh configuration: {exc}") from None
    return zc


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


class Publisher:
    """A reliable, blocking publisher of one topic; counts what it sent."""

    def __init__(self, pub: Any, topic: Topic) -> None:
        self._pub = pub
        self.topic = topic
        self.count = 0

    def put(self, msg: Any) -> bytes:
        data = codec.encode(msg, self.topic.msgtype)
        self.put_raw(data)
        return data

    def put_raw(self, data: bytes) -> None:
        self._pub.put(data)
        self.count += 1


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
        self._missed: list[str] = []
        self._ends: dict[str, float] = {}  # topic -> when its end message showed a shortfall  # samples gone for good (older than the publisher's history)
        self._watched: set[str] = set()
        self._alive_changed = threading.Condition()

    # --- lifecycle -------------------------------------------------------------------------

    def __enter__(self) -> Bus:
        import zenoh

        try:
            self._session = zenoh.open(zenoh_config(self.cfg))
        except Exception as exc:
            raise BusError(f"cannot open Zenoh session ({self.cfg.mode}): {exc}") from None
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
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
        import zenoh

        key = topic.key(self.namespace)
        qos = {"congestion_control": zenoh.CongestionControl.BLOCK, "reliability": zenoh.Reliability.RELIABLE}
        if self.cfg.history:
            import zenoh.ext as zx

            # a bounded cache plus sequence numbers and heartbeats: subscribers detect gaps (a cut
            # link, a reconnect) and fetch the missed samples from this cache
            pub = zx.declare_advanced_publisher(
                self.session, key, **qos, cache=zx.CacheConfig(self.cfg.history),
                sample_miss_detection=zx.MissDetectionConfig(heartbeat=0.5, sporadic_heartbeat=None),
                publisher_detection=True)
        else:
            pub = self.session.declare_publisher(key, **qos)
        self._keep.append(pub)
        return Publisher(pub, topic)

    def subscribe(self, topics: Iterable[Topic]) -> None:
        """Feed these topics into this stage's bounded inbox, in arrival order."""
        import zenoh

        for topic in topics:

            def on_sample(sample: Any, topic: Topic = topic) -> None:
                # Blocking put in Zenoh's receive thread: back-pressure, never a drop.
                self._inbox.put(Received(topic, sample.payload.to_bytes()))

            key, handler = topic.key(self.namespace), zenoh.handlers.Callback(on_sample, indirect=False)
            if self.cfg.history:
                import zenoh.ext as zx

                sub = zx.declare_advanced_subscriber(
                    self.session, key, handler, recovery=zx.RecoveryConfig(periodic_queries=None, heartbeat=True),
                    subscriber_detection=True)

                def on_miss(miss: Any, topic: Topic = topic) -> None:
                    with self._alive_changed:
                        self._missed.append(f"{miss.nb} samples on {topic.key(self.namespace)}")

                listener = sub.sample_miss_listener(zenoh.handlers.Callback(on_miss, indirect=False))
                self._keep.extend([sub, listener])
            else:
                self._keep.append(self.session.declare_subscriber(key, handler))

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
        """`get` a topic from its queryable; the decoded reply, or None if nobody answered."""
        for reply in self.session.get(topic.key(self.namespace), timeout=timeout_s):
            if reply.ok is not None:
                return codec.decode(reply.ok.payload.to_bytes(), topic.msgtype)
        return None

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

    def watch(self, stages: Iterable[str]) -> None:
        """Track the liveliness of peer stages; `check_peers` raises once one disappears."""
        import zenoh

        stages = set(stages)
        self._watched |= stages
        prefix = stage_token("", self.namespace)

        def on_token(sample: Any) -> None:
            name = str(sample.key_expr)[len(prefix):]
            if name not in self._watched:
                return
            with self._alive_changed:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._alive.add(name)
                    self._lost.pop(name, None)  # back after a cut
                else:
                    self._alive.discard(name)
                    self._lost.setdefault(name, time.monotonic())
                self._alive_changed.notify_all()

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
            self._lost.pop(stage, None)

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
            raise StageError(f"{self.stage}: {self._missed[0]} were lost for good (a longer outage than the "
                             f"publisher's history of {self.cfg.history} samples covers)")
        # A vanished producer may come back (a cut link) and, with liveliness and data on different
        # routes, one that sent its last message and left can be seen leaving before that message
        # lands. Only a long absence counts as death.
        now = time.monotonic()
        for stage, since in self._lost.items():
            if now - since > self.cfg.peer_timeout_s:
                raise StageError(f"{self.stage}: the {stage} stage disappeared for {self.cfg.peer_timeout_s:g} s "
                                 f"(process died or link cut)")


def serve_router(listen: tuple[str, ...], *, zenoh_config: str | None = None,
                 stop: threading.Event | None = None) -> None:
    """Host a Zenoh router in this process until `stop` is set (or forever)."""
    cfg = BusConfig(mode="router", listen=listen, zenoh_config=zenoh_config, multicast_scouting=False)
    with Bus(cfg, "router"):
        (stop or threading.Event()).wait()
