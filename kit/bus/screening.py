"""Screening: a sample that is not a sane message is dropped at the bus, counted and shown once.

Every data sample a stage takes is decoded (CDR, the topic's type) and checked (schemas.checks: byte
counts that agree with headers, image headers within any camera's size, rigid poses) before the stage
sees it;
the decoded message rides along, so the stage does not decode twice. A buggy or hostile publisher
cannot crash a stage this way, nor make it allocate what a forged header asks for: its samples are
counted per topic, the first one per publisher is named in the stage's log (a warning), and the rest go silently.

The counts of every bus of this process add up in `totals()`, which the command line hands to
`octolog run` for summary.json. Locking: one lock over the counts (stages screen on their own
thread; a process may hold several buses).
"""

from __future__ import annotations

import dataclasses
import logging
import threading

from octolog.kit.bus import wire
from octolog.kit.bus.inbox import Received
from octolog.kit.errors import InputError
from octolog.schemas import checks

log = logging.getLogger(__name__)
_lock = threading.Lock()
_totals: dict[str, int] = {}  # topic name -> malformed samples dropped, over this process's buses


def totals() -> dict[str, int]:
    """Malformed samples dropped by this process's buses, per topic name."""
    with _lock:
        return dict(sorted(_totals.items()))


class Screening:
    """Decodes and checks each data sample of one bus; drops, counts and reports the bad ones."""

    def __init__(self, stage: str, namespace: str) -> None:
        self._stage, self._namespace = stage, namespace
        self.dropped: dict[str, int] = {}  # topic name -> malformed samples dropped by this bus
        self._shown: set[bytes] = set()  # publishers whose first malformed sample was reported

    def admit(self, item: Received) -> Received | None:
        """`item` with its decoded message, or None if it is malformed (then counted and reported)."""
        if item.query is not None:
            return item
        try:
            msg = checks.checked(item.payload, item.topic.msgtype)
        except InputError as exc:
            self._drop(item, str(exc))
            return None
        return dataclasses.replace(item, msg=msg)

    def _drop(self, item: Received, why: str) -> None:
        name = item.topic.name
        self.dropped[name] = self.dropped.get(name, 0) + 1
        with _lock:
            _totals[name] = _totals.get(name, 0) + 1
        if item.source in self._shown:
            return
        self._shown.add(item.source)
        log.warning("dropped a malformed sample on %s from %s (%d bytes): %s; its further malformed samples "
                    "are counted, not shown", item.topic.key(self._namespace), wire.describe_publisher(item.source),
                    len(item.payload), why, extra={"stage": self._stage})
