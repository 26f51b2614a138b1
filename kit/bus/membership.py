"""Stage membership: who is on the bus, who is gone, who has finished.

Stages announce themselves with liveliness tokens: a producer waits until its consumers are ready,
and every stage notices when a peer stage disappears (process died, link cut) instead of waiting
forever. Only a long absence (`BusConfig.peer_timeout_s`) counts as death: a cut link may heal. A
stage that finishes without error puts a done marker, `<ns>/_octolog/done/<stage>`, so producers
lingering for it may go.

Locking: one Condition, `_changed`, guards everything here (alive, lost, done, watched, followed,
losses) and wakes the waits when a peer comes, goes or finishes. Nothing else is called while it is
held: `on_back` runs after it is released.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable

from octolog.kit.bus.session import Session
from octolog.kit.busconfig import BusConfig
from octolog.kit.errors import StageError
from octolog.schemas.topics import stage_token

log = logging.getLogger(__name__)
SAY_WAITING_S = 5.0  # a wait for other stages longer than this is said (see Membership.wait_for)

DONE = "_octolog/done"  # `<ns>/_octolog/done/<stage>`: put by a stage that finished without error
# `<ns>/_octolog/done/<stage>:<input>`: put by a stage that has taken every sample of one of its inputs
# (the tracker its frames): a producer of that input lingering for it may go while it works on
TAKEN_SEP = ":"


class Membership:
    """One stage's view of its peer stages, and its own announcement."""

    def __init__(self, session: Session, cfg: BusConfig, stage: str, on_back: Callable[[], None]) -> None:
        self._session, self._cfg, self._stage = session, cfg, stage
        self._on_back = on_back  # a lost peer stage is back (after a cut or a restart)
        self._changed = threading.Condition()
        self._alive: set[str] = set()
        self._lost: dict[str, float] = {}  # stage -> monotonic time it vanished
        self._watched: set[str] = set()
        self._followed: set[str] = set()  # tracked like watched ones, but their absence is no error
        self._done: set[str] = set()  # followed stages that said they finished
        self._losses: list[str] = []  # samples gone for good (older than the publisher's history)
        self._fatal: list[str] = []  # what a stage cannot go on with (a publisher over its bound)
        self.announced = False

    def _key(self, key: str) -> str:
        ns = self._cfg.namespace.strip("/")
        return f"{ns}/{key}" if ns else key

    def announce(self) -> None:
        """Declare this stage ready (call after subscribing)."""
        self._session.declare_token(stage_token(self._stage, self._cfg.namespace))
        self.announced = True

    def say_done(self) -> None:
        """Tell the stages lingering for this one that it finished (if it ever announced itself)."""
        if self.announced and self._session.is_open:
            self._session.put_marker(self._key(f"{DONE}/{self._stage}"))

    def say_taken(self, what: str) -> None:
        """Tell the stages lingering for this one's input `what` that it has taken all of it."""
        if self.announced and self._session.is_open:
            self._session.put_marker(self._key(f"{DONE}/{self._stage}{TAKEN_SEP}{what}"))

    def watch(self, stages: Iterable[str], *, required: bool = True) -> None:
        """Track the liveliness of peer stages; `check` raises once a required one has been gone
        for `peer_timeout_s`. A peer that comes back calls `on_back`."""
        stages = set(stages)
        if required:
            self._watched |= stages
        else:
            self._followed |= stages
            done_prefix = self._key(f"{DONE}/")

            def on_done(key: str) -> None:
                with self._changed:
                    self._done.add(key[len(done_prefix):])
                    self._changed.notify_all()

            self._session.subscribe_keys(self._key(f"{DONE}/*"), on_done)
        prefix = stage_token("", self._cfg.namespace)

        def on_token(key: str, alive: bool) -> None:
            name = key[len(prefix):]
            if name not in self._watched and name not in self._followed:
                return
            back = False
            with self._changed:
                if alive:
                    self._alive.add(name)
                    back = self._lost.pop(name, None) is not None  # back after a cut or a restart
                else:
                    self._alive.discard(name)
                    self._lost.setdefault(name, time.monotonic())
                self._changed.notify_all()
            if back:
                self._on_back()

        self._session.watch_tokens(stage_token("*", self._cfg.namespace), on_token)

    def wait_for(self, stages: Iterable[str], timeout_s: float = 30.0) -> None:
        """Block until every named stage has announced itself (they must be watched); a wait longer
        than SAY_WAITING_S is said once (a stage started alone is not silent for a minute)."""
        stages = set(stages)
        start = time.monotonic()
        deadline, said = start + timeout_s, False
        with self._changed:
            while not stages <= self._alive:
                self._raise_if_lost()
                left = deadline - time.monotonic()
                if not said and time.monotonic() - start >= SAY_WAITING_S:
                    said = True
                    log.warning("%s: waiting for the %s stage%s to appear on the bus (namespace %r), up to %.0f s "
                                "more (a stage started on its own waits for the others: start them too, or use `octolog run`)",
                                self._stage, ", ".join(sorted(stages - self._alive)),
                                "s" if len(stages - self._alive) > 1 else "", self._cfg.namespace or "(none)", left)
                if left <= 0:
                    missing = ", ".join(sorted(stages - self._alive))
                    raise StageError(f"{self._stage}: no {missing} stage appeared within {timeout_s:.0f} s "
                                     f"(namespace {self._cfg.namespace or '(none)'!r}; are the stages connected?)")
                self._changed.wait(min(left, 0.5))

    def unwatch(self, stage: str) -> None:
        """Stop caring about a peer (it finished its stream and may leave)."""
        with self._changed:
            self._watched.discard(stage)
            if stage not in self._followed:
                self._lost.pop(stage, None)

    def linger(self, stage: str, poll: Callable[[], None] | None = None, *, taken: str = "") -> bool:
        """Wait until `stage` has finished, or (`taken`) has taken all of that input of its. True once
        it said so; False at once if it never showed up, or once it has been gone for `peer_timeout_s`
        (dead for good: nothing to wait for). `poll` runs between looks, without the lock held (the
        caller draining its inbox)."""
        while True:
            with self._changed:
                if stage in self._done or (taken and f"{stage}{TAKEN_SEP}{taken}" in self._done):
                    return True
                since = self._lost.get(stage)
                if stage not in self._alive and (since is None or time.monotonic() - since > self._cfg.peer_timeout_s):
                    return False
                self._changed.wait(0.1 if poll is not None else 0.5)
            if poll is not None:
                poll()

    def report_loss(self, what: str) -> None:
        """Samples (`what`) are gone for good: the next check raises."""
        with self._changed:
            self._losses.append(what)

    def report_fatal(self, message: str) -> None:
        """Something the stage cannot go on with (`message`, one line): the next check raises."""
        with self._changed:
            self._fatal.append(message)

    def check_fatal(self) -> None:
        """Raise StageError if something fatal was reported (cheap: for every sample received)."""
        if self._fatal:
            raise StageError(self._fatal[0])

    def check(self) -> None:
        """Raise StageError if samples were lost for good or a watched peer is dead."""
        with self._changed:
            self._raise_if_lost()

    def _raise_if_lost(self) -> None:
        self.check_fatal()
        if self._losses:
            raise StageError(f"{self._stage}: {self._losses[0]} were lost for good (the outage outlasted what "
                             f"the publisher keeps in its history)")
        # A vanished producer may come back (a cut link) and, with liveliness and data on different
        # routes, one that sent its last message and left can be seen leaving before that message
        # lands. Only a long absence counts as death.
        now = time.monotonic()
        for stage, since in self._lost.items():
            if stage in self._watched and now - since > self._cfg.peer_timeout_s:
                raise StageError(f"{self._stage}: the {stage} stage disappeared for {self._cfg.peer_timeout_s:g} s "
                                 f"(process died or link cut)")
