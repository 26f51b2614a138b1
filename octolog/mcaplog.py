"""MCAP files in the ROS 2 profile: the only module that reads or writes MCAP.

Schema encoding `ros2msg`, message encoding `cdr`, so files open in rosbags, Rerun, Foxglove and
`ros2 bag`. Configuration, calibration and device info go into metadata records.
"""

from __future__ import annotations

import errno
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from octolog.errors import McapError
from schemas import codec

COMPRESSIONS = ("none", "lz4", "zstd")


@dataclass(frozen=True)
class LoggedMessage:
    topic: str
    msgtype: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int


class McapWriter:
    """Append CDR messages to an MCAP file. Use as a context manager; finishes on exit."""

    def __init__(self, path: str | Path, *, compression: str = "zstd", chunk_size: int = 4 * 1024 * 1024) -> None:
        from mcap.writer import CompressionType, Writer

        if compression not in COMPRESSIONS:
            raise McapError(f"compression {compression!r}: want one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise McapError(f"{self.path}: cannot create: {exc.strerror}") from None
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=getattr(CompressionType, compression.upper()))
        self._writer.start(profile="ros2", library="octolog")
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._seq: dict[int, int] = {}
        self.count = 0
        self._closed = False

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def channel(self, topic: str, msgtype: str) -> int:
        key = (topic, msgtype)
        if key not in self._channels:
            if msgtype not in self._schemas:
                self._schemas[msgtype] = self._writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=codec.msgdef(msgtype).encode()
                )
            self._channels[key] = self._writer.register_channel(
                topic=topic if topic.startswith("/") else "/" + topic,
                message_encoding="cdr",
                schema_id=self._schemas[msgtype],
            )
        return self._channels[key]

    def write(self, topic: str, msgtype: str, data: bytes, *, log_time_ns: int, publish_time_ns: int) -> None:
        cid = self.channel(topic, msgtype)
        seq = self._seq.get(cid, 0)
        self._seq[cid] = seq + 1
        self._guard(lambda: self._writer.add_message(cid, log_time_ns, data, publish_time_ns, seq))
        self.count += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._guard(lambda: self._writer.add_metadata(name, {k: str(v) for k, v in data.items()}))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._guard(self._writer.finish)
        finally:
            self._file.close()

    def _guard(self, fn: Any) -> None:
        try:
            fn()
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                raise McapError(f"{self.path}: disk full after {self.count} messages") from None
            raise McapError(f"{self.path}: write failed: {exc.strerror}") from None


def _open(path: str | Path) -> BinaryIO:
    p = Path(path)
    try:
        return open(p, "rb")  # noqa: SIM115 - callers close
    except FileNotFoundError:
        raise McapError(f"{p}: no such MCAP file") from None
    except OSError as exc:
        raise McapError(f"{p}: cannot open: {exc.strerror}") from None


def read_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[LoggedMessage]:
    """Messages in file order. A truncated or corrupt file raises McapError naming the problem."""
    from mcap.exceptions import McapError as RawMcapError
    from mcap.reader import NonSeekingReader

    wanted = None if topics is None else {t if t.startswith("/") else "/" + t for t in topics}
    p = Path(path)
    n = 0
    with _open(p) as f:
        try:
            reader = NonSeekingReader(f)
            for schema, channel, message in reader.iter_messages():
                if wanted is not None and channel.topic not in wanted:
                    continue
                n += 1
                yield LoggedMessage(channel.topic.lstrip("/"), schema.name if schema else "",
                                    bytes(message.data), message.log_time, message.publish_time, message.sequence)
        except (RawMcapError, EOFError, ValueError, KeyError) as exc:
            raise McapError(f"{p}: truncated or corrupt MCAP after {n} messages ({type(exc).__name__}: {exc}); "
                            f"`octolog info {p}` shows what is readable") from None


@dataclass
class TopicSummary:
    msgtype: str
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0


@dataclass
class McapSummary:
    path: Path
    profile: str = ""
    topics: dict[str, TopicSummary] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = True
    problem: str = ""
    size_bytes: int = 0


def summarize(path: str | Path) -> McapSummary:
    """Scan a whole file: topics, counts, time spans, metadata; reports truncation instead of raising."""
    from mcap.exceptions import McapError as RawMcapError
    from mcap.records import Footer, Header, Message, Metadata
    from mcap.stream_reader import StreamReader

    p = Path(path)
    out = McapSummary(p)
    with _open(p) as f:
        out.size_bytes = p.stat().st_size
        channels: dict[int, tuple[str, str]] = {}
        schemas: dict[int, str] = {}
        from mcap.records import Channel, Schema

        seen_footer = False
        try:
            for rec in StreamReader(f).records:
                if isinstance(rec, Header):
                    out.profile = rec.profile
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = (rec.topic.lstrip("/"), schemas.get(rec.schema_id, ""))
                elif isinstance(rec, Message):
                    topic, msgtype = channels[rec.channel_id]
                    ts = out.topics.setdefault(topic, TopicSummary(msgtype, first_ns=rec.log_time))
                    ts.count += 1
                    ts.first_ns = min(ts.first_ns, rec.log_time)
                    ts.last_ns = max(ts.last_ns, rec.log_time)
                elif isinstance(rec, Metadata):
                    out.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    seen_footer = True
        except (RawMcapError, EOFError, ValueError, KeyError) as exc:
            out.complete = False
            out.problem = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if out.complete and not seen_footer:
            out.complete = False
            out.problem = "no footer (recording did not finish)"
    return out
