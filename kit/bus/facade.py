"""`Bus`: one stage's connection to the others, composed of the bus's parts.

The parts own their state and locks: `Session` (Zenoh), `Publishing` (numbered publishers and
their histories), `InOrderDelivery` (subscriptions into the `Inbox`, gap repair), `Membership`
(liveliness, done markers). `Bus` only wires them together (a loss found by delivery fails the
stage through membership; a peer that is back makes delivery catch up) and holds no lock itself.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from octolog.kit.bus.delivery import InOrderDelivery
from octolog.kit.bus.inbox import Inbox, Received
from octolog.kit.bus.membership import Membership
from octolog.kit.bus.publishing import Publisher, Publishing
from octolog.kit.bus.screening import Screening
from octolog.kit.bus.session import Query, Session, ZenohSession
from octolog.kit.busconfig import BusConfig
from octolog.kit.errors import InputError
from octolog.schemas import codec
from octolog.schemas.topics import Topic

WAKE_S = 0.2  # a thread blocked on an event wakes this often, so signal handlers run (wait_interruptibly)


class Bus:
    """One Zenoh session for one stage. Use as a context manager.

    `inbox_size`: samples waiting for the stage before delivery waits (back-pressure on the
    producers through Zenoh); 0: unbounded, delivery never waits (see `Inbox`)."""

    def __init__(self, cfg: BusConfig, stage: str, *, inbox_size: int = 8) -> None:
        self.cfg = cfg
        self.stage = stage
        self.namespace = cfg.namespace
        self._session = Session(cfg)
        self._inbox = Inbox(inbox_size)
        self._publishing = Publishing(self._session, cfg, stage)
        self._membership = Membership(self._session, cfg, stage, on_back=self._catch_up)
        self._delivery = InOrderDelivery(self._session, cfg, stage, self._inbox,
                                         on_loss=self._membership.report_loss,
                                         on_fatal=self._membership.report_fatal)
        self._screening = Screening(stage, cfg.namespace)

    def _catch_up(self) -> None:
        self._delivery.catch_up()

    # --- lifecycle -------------------------------------------------------------------------

    def __enter__(self) -> Bus:
        self._session.open()
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            # finished, not crashed: producers lingering for this stage may go (see `linger`)
            self._membership.say_done()
        self.close()

    def close(self) -> None:
        self._inbox.close()
        self._delivery.close()
        self._session.close()

    @property
    def session(self) -> ZenohSession:
        """The Zenoh session (BusError if the bus is not open)."""
        return self._session.zenoh

    @property
    def malformed(self) -> dict[str, int]:
        """Samples dropped as malformed, per topic name (see `octolog.kit.bus.screening`)."""
        return dict(self._screening.dropped)

    @property
    def held_mb(self) -> float:
        """MB of samples held behind gaps now (bounded by `BusConfig.max_held_mb`)."""
        return self._delivery.held_bytes / 2**20

    @property
    def recovered(self) -> int:
        """Samples that came from a history rather than live."""
        return self._delivery.recovered

    # --- data ------------------------------------------------------------------------------

    def publisher(self, topic: Topic) -> Publisher:
        """A reliable, blocking publisher of `topic` (numbered, with a history, if history is on)."""
        return self._publishing.publisher(topic)

    def subscribe(self, topics: Iterable[Topic], *, latest_only: Iterable[Topic] = ()) -> None:
        """Feed these topics into this stage's inbox: per publisher exactly once and in
        order (with history), as they arrive across topics. Samples of a `latest_only` topic in a
        row collapse to the newest while they wait (progress signals: they never fill the inbox)."""
        for topic in latest_only:
            self._inbox.keep_latest(topic)
        self._delivery.subscribe(topics)

    def receive(self, timeout_s: float = 0.25) -> Received | None:
        """The next sample, decoded and checked (`Received.decode()` costs nothing), or None after
        `timeout_s`; malformed samples are dropped on the way (`malformed`). Raises StageError if a
        watched peer died or a publisher went over a bound."""
        deadline = time.monotonic() + timeout_s
        while True:
            item = self._inbox.get(max(0.0, deadline - time.monotonic()))
            if item is None:
                self.check_peers()
                return None
            self._membership.check_fatal()
            item = self._screening.admit(item)
            if item is not None:
                return item

    def receive_nowait(self) -> Received | None:
        """The next sample if one is waiting (decoded and checked), else None."""
        while (item := self._inbox.get_nowait()) is not None:
            item = self._screening.admit(item)
            if item is not None:
                return item
        return None

    def listen(self, topic: Topic, on_msg: Callable[[Any], None]) -> None:
        """Call `on_msg(message)` on Zenoh's receive thread for each sample of `topic`, outside the
        inbox and its ordering: for a small side stream a stage only glances at (an IMU at 200 Hz
        must not queue up between keyframes). Samples that do not decode are ignored."""

        def on_sample(payload: bytes, _attachment: bytes | None) -> None:
            try:
                msg = codec.decode(payload, topic.msgtype)
            except InputError:
                return
            on_msg(msg)

        self._session.subscribe(topic.key(self.namespace), on_sample)

    def serve(self, topic: Topic, latest: Callable[[], bytes | None]) -> None:
        """Answer `get` on this topic's key with `latest()` (CDR bytes), e.g. the current map."""
        key = topic.key(self.namespace)

        def on_query(query: Query) -> None:
            data = latest()
            if data is not None:
                query.reply(key, data)

        self._session.declare_queryable(key, on_query, indirect=False)

    def accept(self, topic: Topic) -> None:
        """Take queries on this topic's key into the inbox, in order with the data, to be answered
        by the stage's own loop (e.g. "save the map now")."""

        def on_query(query: Query) -> None:
            self._inbox.put_request(Received(topic, b"", query))

        self._session.declare_queryable(topic.key(self.namespace), on_query, indirect=False)

    def fetch(self, topic: Topic, timeout_s: float = 10.0) -> Any | None:
        """`get` a topic from its queryable; the decoded reply, or None if nobody answered (within
        the timeout, including the time a fresh session takes to learn of the queryable)."""
        data = self._session.fetch(topic.key(self.namespace), timeout_s)
        return None if data is None else codec.decode(data, topic.msgtype)

    def expect_count(self, topic: Topic, received: int, announced: int) -> None:
        """After a stream's end message: raise StageError once a shortfall is final (see
        `InOrderDelivery.expect_count`)."""
        self._delivery.expect_count(topic, received, announced)

    # --- stages: readiness and liveness ------------------------------------------------------

    def start(self, topics: Iterable[Topic], *, wait_for: Iterable[str] = (), timeout_s: float = 60.0,
              latest_only: Iterable[Topic] = ()) -> None:
        """The usual stage start: subscribe, wait for the stages named, then announce readiness."""
        self.subscribe(topics, latest_only=latest_only)
        wait_for = tuple(wait_for)
        self.watch(wait_for)
        self.wait_for(wait_for, timeout_s)
        self.announce()

    def announce(self) -> None:
        """Declare this stage ready (call after subscribing)."""
        self._membership.announce()

    def watch(self, stages: Iterable[str], *, required: bool = True) -> None:
        """Track the liveliness of peer stages; `check_peers` raises once a required one has been
        gone for `peer_timeout_s`. A peer that comes back makes the subscribers catch up at once."""
        self._membership.watch(stages, required=required)

    def wait_for(self, stages: Iterable[str], timeout_s: float = 30.0) -> None:
        """Block until every named stage has announced itself (they must be watched)."""
        self._membership.wait_for(stages, timeout_s)

    def unwatch(self, stage: str) -> None:
        """Stop caring about a peer (it finished its stream and may leave)."""
        self._membership.unwatch(stage)

    def say_taken(self, what: str) -> None:
        """Tell producers lingering for this stage's input `what` (`linger(..., taken=what)`) that it
        has taken every sample of it: they may go while this stage works on."""
        self._membership.say_taken(what)

    def linger(self, stage: str, on_received: Callable[[Received], None] | None = None, *,
               taken: str = "") -> bool:
        """Stay up, histories and all, until `stage` has finished, so that a consumer restarted
        meanwhile still recovers everything it needs. Follow the stage from the start
        (`watch([stage], required=False)`).

        What this stage's subscriptions still receive meanwhile goes to `on_received` (default:
        dropped): left in a full inbox it would block the receive thread, and with it the very
        news that `stage` finished.

        With `taken` (an input of `stage`), until it has taken all of that input, or finished.

        Returns True once it said it finished; False at once if it never showed up, or once it has
        been gone for `peer_timeout_s` (dead for good: nothing left to wait for).
        """
        def drain() -> None:
            while (r := self.receive_nowait()) is not None:
                if on_received is not None:
                    on_received(r)

        return self._membership.linger(stage, drain, taken=taken)

    def check_peers(self) -> None:
        """Raise StageError if samples were lost for good or a watched peer stage is dead."""
        self._membership.check()


def serve_router(listen: tuple[str, ...], *, connect: tuple[str, ...] = (), zenoh_config: str | None = None,
                 stop: threading.Event | None = None, ready: Callable[[], None] | None = None) -> None:
    """Host a Zenoh router in this process until `stop` is set (or forever), joined to the routers
    in `connect`; `ready()` is called once its session is open."""
    cfg = BusConfig(mode="router", listen=listen, connect=connect, zenoh_config=zenoh_config,
                    multicast_scouting=False)
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
