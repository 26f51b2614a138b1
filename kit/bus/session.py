"""The Zenoh session of one bus: the only module that imports zenoh.

`Session` opens and closes the session and declares everything on it with the options the wire
contract fixes (reliable, congestion control BLOCK; callbacks on Zenoh's receive thread unless
said otherwise), handing the rest of the bus plain bytes, strings and booleans. What it declares
stays declared until the session closes.

Locking: none of its own. It is opened and closed by the bus's owner thread; Zenoh's session and
the declarations list may be used from any thread (list appends are atomic).
"""

from __future__ import annotations

import json
import os
import re
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import zenoh
import zenoh.ext

from octolog.kit.bus.diagnose import diagnosis
from octolog.kit.busconfig import BusConfig
from octolog.kit.errors import BusError

_BLOCK_CLOSE = "transport/link/tx/queue/congestion_control/block/wait_before_close"
_ZENOH_DEFAULT_BLOCK_CLOSE_US = 5_000_000
CONNECT_TIMEOUT_MS = 30_000
BLOCK_CLOSE_US = 600_000_000  # a consumer stalled for 10 minutes is dead, not slow

# zenoh's types under names the rest of the bus may use (only this module imports zenoh); also
# what `Session`'s annotations use, where `zenoh` names its property
ZenohConfig = zenoh.Config
ZenohSession = zenoh.Session
ZenohPublisher = zenoh.Publisher
LatchedPublisher = zenoh.ext.AdvancedPublisher
Query = zenoh.Query
ZenohSample = zenoh.Sample
_Kept = TypeVar("_Kept")


def zenoh_config(cfg: BusConfig) -> ZenohConfig:
    """The Zenoh configuration for `cfg`: its JSON5 file if any, with our flags on top; BusError if
    the file or a value is invalid."""
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
        if cfg.ros2_domain >= 0:
            # latched ROS 2 topics (/tf_static) keep their last sample in a zenoh-ext cache, which
            # orders samples by timestamp: rmw_zenoh's default configs turn timestamping on too
            zc.insert_json5("timestamping/enabled", "true")
    except Exception as exc:  # zenoh raises ZError with the parser's message, over several lines
        where = f" {cfg.zenoh_config}" if cfg.zenoh_config else ""
        raise BusError(f"invalid Zenoh configuration{where}: {one_line(exc)}") from None
    return zc


def ext_serialize(items: tuple[str | int | bytes, ...]) -> bytes:
    """`items` in zenoh-ext's serialisation, ints as int64 (rmw_zenoh's attachment, kit/bus/ros2.py)."""
    return zenoh.ext.z_serialize(tuple(zenoh.ext.Int64(v) if isinstance(v, int) else v for v in items)).to_bytes()


def ext_deserialize(data: bytes, kinds: tuple[type, ...]) -> tuple[Any, ...]:
    """What `ext_serialize` made of items of `kinds` (str, int, bytes); ValueError if `data` is not that."""
    spec = tuple[tuple(zenoh.ext.Int64 if kind is int else kind for kind in kinds)]  # type: ignore[misc]
    try:
        values = zenoh.ext.z_deserialize(spec, zenoh.ZBytes(data))
    except zenoh.ext.ZDeserializeError as exc:
        raise ValueError(str(exc)) from None
    return tuple(int(v) if kind is int else v for kind, v in zip(kinds, values, strict=True))


def one_line(exc: BaseException) -> str:
    """Zenoh's multi-line parser messages as one line: position and reason, no source paths."""
    lines = [ln.strip(" |=") for ln in str(exc).splitlines()]
    text = " ".join(ln for ln in lines if ln and ln != "^---")
    return re.sub(r" at /\S+\.rs:\d+\.?", "", text).strip()


class Session:
    """One Zenoh session, not yet open; `open` it, `close` it. Every method but `open` and `close`
    raises BusError while it is not open."""

    def __init__(self, cfg: BusConfig) -> None:
        self.cfg = cfg
        self._zenoh: ZenohSession | None = None
        self._declared: list[object] = []  # publishers, subscribers, queryables, tokens: kept alive

    def open(self) -> None:
        if os.environ.get("RUST_LOG"):  # Zenoh's own log (link open/close, lease expiry) on demand
            zenoh.try_init_log_from_env()
        zc = zenoh_config(self.cfg)  # a BusError of its own for a bad configuration
        try:
            self._zenoh = zenoh.open(zc)
        except Exception as exc:
            why = diagnosis(zc) if self.cfg.mode == "client" else ""
            raise BusError(f"cannot open Zenoh session ({self.cfg.mode}): {one_line(exc)}"
                           + (f"; {why}" if why else "")) from None

    @property
    def is_open(self) -> bool:
        return self._zenoh is not None

    @property
    def zenoh(self) -> ZenohSession:
        """The Zenoh session itself."""
        if self._zenoh is None:
            raise BusError("bus is not open")
        return self._zenoh

    def zid(self) -> str:
        """The session's Zenoh id (hex), as the ROS graph's tokens name it."""
        return str(self.zenoh.info.zid())

    def close(self) -> None:
        """Undeclare everything and close the session (no-op if it is not open)."""
        if self._zenoh is not None:
            self._declared.clear()
            try:
                self._zenoh.close()
            finally:
                self._zenoh = None

    def _keep(self, entity: _Kept) -> _Kept:
        self._declared.append(entity)
        return entity

    # --- data -------------------------------------------------------------------------------

    def declare_publisher(self, key: str) -> ZenohPublisher:
        """A reliable publisher that blocks when the link is congested (never drops)."""
        return self._keep(self.zenoh.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE))

    def declare_latched_publisher(self, key: str, depth: int = 1) -> LatchedPublisher:
        """A reliable, blocking publisher that keeps its last `depth` samples for subscribers that
        join later and ask for history (zenoh-ext's AdvancedPublisher, as rmw_zenoh declares a
        TRANSIENT_LOCAL publisher), and can be detected by them (liveliness)."""
        return self._keep(zenoh.ext.declare_advanced_publisher(
            self.zenoh, key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE,
            cache=zenoh.ext.CacheConfig(depth), publisher_detection=True))

    def subscribe(self, key: str, on_sample: Callable[[bytes, bytes | None], None]) -> None:
        """Call `on_sample(payload, attachment)` on Zenoh's receive thread for each sample on `key`,
        so that a blocking callback pushes back on the link."""

        def on_zenoh_sample(sample: ZenohSample) -> None:
            att = sample.attachment
            on_sample(sample.payload.to_bytes(), None if att is None else att.to_bytes())

        self._keep(self.zenoh.declare_subscriber(key, zenoh.handlers.Callback(on_zenoh_sample, indirect=False)))

    def subscribe_keys(self, key: str, on_key: Callable[[str], None]) -> None:
        """Call `on_key(key)` for each sample on `key` (a key expression): markers without payload."""
        self._keep(self.zenoh.declare_subscriber(
            key, zenoh.handlers.Callback(lambda sample: on_key(str(sample.key_expr)), indirect=False)))

    def put_marker(self, key: str) -> None:
        """Put an empty sample on `key`, blocking until it is on its way."""
        self.zenoh.put(key, b"", congestion_control=zenoh.CongestionControl.BLOCK)

    # --- queries ----------------------------------------------------------------------------

    def declare_queryable(self, key: str, on_query: Callable[[Query], None], *, indirect: bool) -> None:
        """Answer queries on `key` with `on_query`: on Zenoh's receive thread, or with `indirect`
        on a thread of its own (for answers that may be large or block)."""
        self._keep(self.zenoh.declare_queryable(key, zenoh.handlers.Callback(on_query, indirect=indirect)))

    def get(self, selector: str, timeout_s: float) -> Iterator[tuple[bytes, bytes]]:
        """Every answer to `selector`, unconsolidated: (payload, attachment or b"") per reply that is
        not an error."""
        for reply in self.zenoh.get(selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
            ok = reply.ok
            if ok is not None:
                yield ok.payload.to_bytes(), ok.attachment.to_bytes() if ok.attachment is not None else b""

    def fetch(self, key: str, timeout_s: float) -> bytes | None:
        """The first answer from a queryable on `key`, or None if nobody answered.

        A session that has just opened may not know the queryable yet (declarations arrive
        after the link): a plain `get` then returns at once with nothing. So wait, up to the
        timeout, until a matching queryable is known, then ask.
        """
        deadline = time.monotonic() + timeout_s
        querier = self.zenoh.declare_querier(key, timeout=timeout_s)
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
                    return reply.ok.payload.to_bytes()
            return None
        finally:
            if listener is not None:
                listener.undeclare()
            querier.undeclare()

    # --- liveliness -------------------------------------------------------------------------

    def declare_token(self, key: str) -> None:
        """A liveliness token on `key`, alive until the session closes (or the link is cut)."""
        self._keep(self.zenoh.liveliness().declare_token(key))

    def watch_tokens(self, key: str, on_change: Callable[[str, bool], None]) -> None:
        """Call `on_change(token key, alive)` for the tokens matching `key`: first those alive now,
        then each appearance and disappearance."""

        def on_token(sample: ZenohSample) -> None:
            on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        self._keep(self.zenoh.liveliness().declare_subscriber(
            key, zenoh.handlers.Callback(on_token, indirect=False), history=True))
