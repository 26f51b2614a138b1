"""The recovery protocol's bytes and keys: sample numbering and history queries.

Both ends of the protocol live here, so the publisher that writes a field and the subscriber that
reads it cannot drift apart. Pure functions and constants: no Zenoh, no state, no locks.

A numbered sample's attachment is its seq (u64 LE), its publisher id (16 bytes) and its
dependencies: for each other numbered publisher of the same bus that had sent something, that
publisher's id, the crc32 of its key and its count then. A subscriber delivers a sample only after
everything it depends on among the keys it takes, so the topics of one stage keep their order (a
pose correction never overtakes the keyframes it corrects). History replies prepend the oldest seq
the publisher still keeps, so a subscriber can tell late from lost.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

_HEAD = struct.Struct("<Q16sH")
_DEP = struct.Struct("<16sIQ")
_OLDEST = struct.Struct("<Q")
HISTORY = "@history"  # a verbatim chunk: `**` subscribers and queries never match it by accident
BATCH = 16  # samples per history reply: a large backlog comes in several queries

Dependency = tuple[bytes, int, int]  # publisher id, crc32 of its key, its count when this was sent


class QueryParameters(Protocol):
    """A query's `?a=1;b=2` parameters, as Zenoh hands them to a queryable."""

    def get(self, key: str, /) -> str | None: ...


@dataclass(frozen=True)
class Numbered:
    """What a numbered attachment says about its sample."""

    seq: int
    source: bytes  # the publisher id
    deps: tuple[Dependency, ...]


def publisher_id(stage: str, unique: bytes) -> bytes:
    """A publisher id: the first 8 bytes of its stage's name (for messages; anyone can claim any
    name, access control says who may publish), then 8 unique bytes."""
    return stage.encode()[:8].ljust(8, b"\0") + unique[:8]


def describe_publisher(source: bytes) -> str:
    """How messages name a publisher: `publisher replay/1a2b3c4d`, or an unnumbered one."""
    if not source:
        return "a publisher without octolog numbering"
    name = "".join(c if c.isalnum() or c in "-_" else "?" for c in source[:8].rstrip(b"\0").decode("ascii", "replace"))
    return f"publisher {name}/{source[8:12].hex()}"


def key_crc(key: str) -> int:
    """How a dependency names the key its publisher sends on."""
    return zlib.crc32(key.encode())


def dependency(source: bytes, crc: int, count: int) -> bytes:
    """One dependency, packed: another publisher had sent `count` samples on the key with `crc`."""
    return _DEP.pack(source, crc, count)


def numbered_attachment(seq: int, source: bytes, deps: list[bytes]) -> bytes:
    """The attachment of sample `seq` of publisher `source`, with its packed dependencies."""
    return _HEAD.pack(seq, source, len(deps)) + b"".join(deps)


def parse_numbered(raw: bytes) -> Numbered | None:
    """seq, publisher id, dependencies of a numbered attachment; None if it is not one of ours."""
    if len(raw) < _HEAD.size:
        return None
    seq, source, n = _HEAD.unpack_from(raw)
    if len(raw) != _HEAD.size + n * _DEP.size:
        return None
    return Numbered(seq, source, tuple(_DEP.unpack_from(raw, _HEAD.size + i * _DEP.size) for i in range(n)))


def history_key(key: str, source: bytes) -> str:
    """Where publisher `source` of `key` serves its history."""
    return f"{key}/{HISTORY}/{source.hex()}"


def history_selector(key: str, wants: Iterable[tuple[bytes, int, int | None]]) -> str:
    """A query for every history of `key`: `?from=0;<id>=F[:U]` asks publisher <id> for its samples
    F.. (before U), any other publisher for everything it keeps."""
    parts = [f"{src.hex()}={first}" + (f":{until}" if until is not None else "") for src, first, until in wants]
    return f"{key}/{HISTORY}/*?from=0" + "".join(f";{p}" for p in parts)


def requested_range(params: QueryParameters, source: bytes) -> tuple[int, int | None] | None:
    """From a history query's parameters: the first seq publisher `source` should send and the seq
    it may stop before; None if the query is malformed."""
    first, _, until = (params.get(source.hex()) or params.get("from") or "0").partition(":")
    try:
        return int(first), int(until) if until else None
    except ValueError:
        return None


def history_attachment(oldest: int, attachment: bytes) -> bytes:
    """A history reply's attachment: the oldest seq kept, then the sample's own attachment."""
    return _OLDEST.pack(oldest) + attachment


def parse_history_reply(raw: bytes) -> tuple[int, Numbered] | None:
    """The oldest seq kept and the numbering of a history reply; None if it is not one of ours."""
    numbered = parse_numbered(raw[_OLDEST.size:]) if len(raw) > _OLDEST.size else None
    if numbered is None:
        return None
    return _OLDEST.unpack_from(raw)[0], numbered
