"""MCAP files in the ROS 2 profile: the only module that reads or writes MCAP.

Schema encoding `ros2msg`, message encoding `cdr`, so files open in rosbags, Rerun, Foxglove and
`ros2 bag`. Configuration, calibration and device info go into metadata records.
"""

from __future__ import annotations

import errno
import os
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO

from mcap.data_stream import RecordBuilder
from mcap.exceptions import McapError as RawMcapError
from mcap.reader import NonSeekingReader
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from zstandard import ZstdError

from octolog.kit.errors import InputError, McapError
from octolog.kit.recordfile import RecordFile
from octolog.schemas import codec, logview
from octolog.schemas.topics import BY_NAME

# What the mcap reader and its decompressors raise on damaged bytes (found by tests/kit/test_fuzz.py:
# lz4 raises RuntimeError for a cut frame, a header shorter than the magic struct.error, zstandard
# its own ZstdError): each one means "this file is damaged here", never a crash.
_DAMAGE: tuple[type[BaseException], ...] = (RawMcapError, EOFError, ValueError, KeyError, IndexError, struct.error,
                                            RuntimeError, OverflowError, ZstdError)

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
    """Append CDR messages to an MCAP file. Use as a context manager; finishes on exit.

    Crash-safe by construction: chunks go to disk whole as they fill, so a killed writer leaves
    every finished chunk readable (`salvage` copies them into a complete file). A failed write
    (e.g. disk full) leaves the file on a record boundary; `close` then ends it with a footer
    and no index (readers scan it), so it stays readable.
    """

    def __init__(self, path: str | Path, *, compression: str = "zstd", chunk_size: int = 4 * 1024 * 1024) -> None:
        if compression not in COMPRESSIONS:
            raise McapError(f"compression {compression!r}: want one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = RecordFile(self.path)
        except OSError as exc:
            raise McapError(f"{self.path}: cannot create: {exc.strerror}") from None
        self._writer = Writer(self._file, chunk_size=chunk_size,  # type: ignore[arg-type]
                              compression=getattr(CompressionType, compression.upper()))
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._raw_schemas: dict[tuple[str, str, bytes], int] = {}
        self._seq: dict[int, int] = {}
        self.count = 0
        self.flushed_count = 0  # messages known to be in the file (in chunks already written)
        self.failed = False  # a write failed; the file ends before it
        self._closed = False
        self._guard(lambda: self._writer.start(profile="ros2", library="octolog"))

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        try:
            self.close()
        except McapError:
            if exc_type is None:
                raise
            # the error that stopped the writing says more than a failed finish after it

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
        self.write_channel(cid, data, log_time_ns=log_time_ns, publish_time_ns=publish_time_ns, sequence=seq)

    def register_raw(self, topic: str, *, schema_name: str, schema_encoding: str, schema_data: bytes,
                     message_encoding: str) -> int:
        """A channel with a schema given verbatim (copying another file's channels); its id."""
        key = (schema_name, schema_encoding, bytes(schema_data))
        if key not in self._raw_schemas:
            self._raw_schemas[key] = self._writer.register_schema(
                name=schema_name, encoding=schema_encoding, data=bytes(schema_data)) if schema_name else 0
        return int(self._writer.register_channel(topic=topic, message_encoding=message_encoding,
                                                 schema_id=self._raw_schemas[key]))

    def write_channel(self, cid: int, data: bytes, *, log_time_ns: int, publish_time_ns: int, sequence: int) -> None:
        """Append one message to a registered channel."""
        if self.failed:
            raise McapError(f"{self.path}: not writable after an earlier write failure")
        before = self._file.tell()
        self._guard(lambda: self._writer.add_message(cid, log_time_ns, data, publish_time_ns, sequence))
        self.count += 1
        if self._file.tell() != before:  # a chunk went to disk, this message with it
            self.flushed_count = self.count

    @property
    def size_bytes(self) -> int:
        """Bytes in the file so far (the open chunk is not counted until it is written)."""
        return self._file.tell()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._guard(lambda: self._writer.add_metadata(name, {k: str(v) for k, v in data.items()}))

    def close(self) -> None:
        """Finish the file: index and footer; after a failed write, a footer without index."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.failed:
                self._end_without_index()
            else:
                self._guard(self._writer.finish)
                self.flushed_count = self.count
        finally:
            self._file.close()

    def _end_without_index(self) -> None:
        # mcap's Writer state after a failed chunk write is inconsistent (its indexes name the lost
        # chunk), so its finish() must not run. DataEnd + a footer with no summary is a complete
        # MCAP file: readers without a summary scan the data section.
        rb = RecordBuilder()
        DataEnd(0).write(rb)
        Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
        try:
            self._file.write(rb.end() + MCAP0_MAGIC)
        except OSError as exc:
            raise McapError(f"{self.path}: cannot finish after a failed write ({exc.strerror}); "
                            f"`octolog recover {self.path} OUT.mcap` gets back what was written") from None

    def _guard(self, fn: Callable[[], object]) -> None:
        try:
            fn()
        except OSError as exc:
            self.failed = True
            if exc.errno == errno.ENOSPC:
                raise McapError(f"disk full: {self.path} after {self.count} messages (no space left on the disk "
                                f"holding {self.path.parent})") from None
            raise McapError(f"{self.path}: write failed: {exc.strerror}") from None


class _Clamped:
    """A file whose reads never ask for more than what is left: the mcap reader reads a record's
    declared length at once, and Python allocates a read's whole size first, so a forged length
    (2 GB in a 5 kB file) would allocate that much before finding the file short (tests/kit/test_fuzz.py)."""

    def __init__(self, f: BinaryIO) -> None:
        self._f = f
        self._size = os.fstat(f.fileno()).st_size

    def read(self, n: int = -1) -> bytes:
        left = max(0, self._size - self._f.tell())
        return self._f.read(left if n is None or n < 0 else min(n, left))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


def _open(path: str | Path) -> BinaryIO:
    p = Path(path)
    try:
        return open(p, "rb")  # noqa: SIM115 - callers close
    except FileNotFoundError:
        raise McapError(f"{p}: no such MCAP file") from None
    except OSError as exc:
        raise McapError(f"{p}: cannot open: {exc.strerror}") from None


def _require_magic(f: BinaryIO, p: Path) -> None:
    """McapError unless `f` starts with the MCAP magic: random bytes are no recording, not a damaged one."""
    head = f.read(len(MCAP0_MAGIC))
    f.seek(0)
    if head != MCAP0_MAGIC:
        what = "an empty file" if not head else "no MCAP magic at its start"
        raise McapError(f"{p}: not an MCAP file ({what}); nothing to read")


def _summary_section(path: str | Path) -> Any:
    """A complete file's summary section (read from its end, not scanned); None when the file has no
    statistics (truncated, or written without a summary)."""
    from mcap.reader import make_reader

    try:
        with _open(path) as f:
            summary = make_reader(_Clamped(f)).get_summary()
    except (*_DAMAGE, OSError):
        return None
    return None if summary is None or summary.statistics is None else summary


def message_counts(path: str | Path) -> dict[str, int] | None:
    """Messages per topic from a complete file's summary section (read from its end, not scanned);
    None when the file has no statistics (truncated, or written without a summary)."""
    if (summary := _summary_section(path)) is None:
        return None
    channels = summary.channels
    return {channels[c].topic.lstrip("/"): n for c, n in summary.statistics.channel_message_counts.items()
            if c in channels}


def time_span(path: str | Path) -> tuple[int, int] | None:
    """The log times of a complete file's first and last message (ns), from its summary section;
    None as for `message_counts`."""
    if (summary := _summary_section(path)) is None or not summary.statistics.message_count:
        return None
    return summary.statistics.message_start_time, summary.statistics.message_end_time


def damaged(path: str | Path, problem: str) -> str:
    """The one-line message for a truncated or corrupt MCAP file: what is wrong and what saves it."""
    stem = Path(path).name.removesuffix(".mcap")
    return (f"{path}: truncated or corrupt MCAP ({problem}); `octolog info {path}` shows what is readable, "
            f"`octolog recover {path} {stem}-recovered.mcap` saves it to a complete file")


def read_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[LoggedMessage]:
    """Messages in file order. A truncated or corrupt file raises McapError naming the problem."""
    wanted = None if topics is None else {t if t.startswith("/") else "/" + t for t in topics}
    p = Path(path)
    n = 0
    with _open(p) as f:
        try:
            reader = NonSeekingReader(_Clamped(f))
            # the topics go to the reader: iterating every message and skipping here holds the whole
            # file in memory until the end (mcap 1.6: +200 MB for a 191 MB log; 11 GB after 10 minutes)
            for schema, channel, message in reader.iter_messages(topics=sorted(wanted) if wanted is not None else None):
                if wanted is not None and channel.topic not in wanted:
                    continue
                n += 1
                yield LoggedMessage(channel.topic.lstrip("/"), schema.name if schema else "",
                                    bytes(message.data), message.log_time, message.publish_time, message.sequence)
        except _DAMAGE as exc:
            raise McapError(damaged(p, f"after {n} messages: {type(exc).__name__}: {exc}")) from None


def read_wire(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[LoggedMessage]:
    """A session log's messages as the bus carried them (wire topics and types, in file order).

    The log stores each octolog_msgs message as standard-typed parts followed by a DiagnosticArray
    on the wire topic (octolog.schemas.logview); here they are joined back into the exact wire
    bytes, stamped with the DiagnosticArray's log time. The parts themselves are not yielded. A log
    written before the standard view (wire types stored as they are) reads the same.
    """
    names = None if topics is None else [t.lstrip("/") for t in topics]
    want = None
    if names is not None:
        want = set(names)
        for name in names:
            if name in BY_NAME:
                want.update(logview.part_topics(BY_NAME[name].msgtype))
    all_parts = {p.topic for parts in logview.PARTS.values() for p in parts}
    pending: dict[str, bytes] = {}
    for m in read_messages(path, want):
        if m.topic in all_parts and m.msgtype != logview.DIAGNOSTICS:
            pending[m.topic] = m.data
            if names is not None and m.topic in names:
                yield m
            continue
        if m.msgtype == logview.DIAGNOSTICS:
            wire = logview.wire_type(codec.decode(m.data, logview.DIAGNOSTICS))
            if wire is not None:
                parts = {t: pending.pop(t) for t in logview.part_topics(wire) if t in pending}
                try:
                    data = logview.join(wire, m.data, parts)
                except InputError as exc:
                    raise InputError(f"{path}: /{m.topic} message {m.sequence}: {exc}") from None
                m = LoggedMessage(m.topic, wire, data, m.log_time_ns, m.publish_time_ns, m.sequence)
        if names is None or m.topic in names:
            yield m


@dataclass
class TopicSummary:
    msgtype: str
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0
    intervals_ns: list[int] = field(default_factory=list, repr=False)  # between consecutive log times

    def gaps(self, factor: float = 1.5) -> tuple[int, int]:
        """(number of intervals longer than `factor` x the median interval, longest interval in ns)."""
        if len(self.intervals_ns) < 2:
            return 0, max(self.intervals_ns, default=0)
        ordered = sorted(self.intervals_ns)
        median = ordered[len(ordered) // 2]
        return sum(1 for d in self.intervals_ns if d > factor * median), ordered[-1]


@dataclass
class McapSummary:
    path: Path
    profile: str = ""
    topics: dict[str, TopicSummary] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = True
    problem: str = ""
    size_bytes: int = 0

    @property
    def wire_topics(self) -> dict[str, TopicSummary]:
        """The topics as the bus carried them: a DiagnosticArray standing for an octolog type on its
        wire topic (octolog.schemas.logview) is listed with the wire type; the parts stay listed."""
        out = {}
        for name, ts in self.topics.items():
            wire = BY_NAME.get(name)
            if ts.msgtype == logview.DIAGNOSTICS and wire is not None and logview.is_split(wire.msgtype):
                ts = replace(ts, msgtype=wire.msgtype)
            out[name] = ts
        return out


def summarize(path: str | Path) -> McapSummary:
    """Scan a whole file: topics, counts, time spans, metadata; reports truncation instead of raising.

    A file that is not MCAP at all (no magic) raises McapError."""
    p = Path(path)
    out = McapSummary(p)
    with _open(p) as f:
        _require_magic(f, p)
        out.size_bytes = p.stat().st_size
        channels: dict[int, tuple[str, str]] = {}
        schemas: dict[int, str] = {}
        seen_footer = False
        try:
            for rec in StreamReader(_Clamped(f)).records:
                if isinstance(rec, Header):
                    out.profile = rec.profile
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = (rec.topic.lstrip("/"), schemas.get(rec.schema_id, ""))
                elif isinstance(rec, Message):
                    topic, msgtype = channels[rec.channel_id]
                    ts = out.topics.setdefault(topic, TopicSummary(msgtype, first_ns=rec.log_time))
                    if ts.count:
                        ts.intervals_ns.append(rec.log_time - ts.last_ns)
                    ts.count += 1
                    ts.first_ns = min(ts.first_ns, rec.log_time)
                    ts.last_ns = max(ts.last_ns, rec.log_time)
                elif isinstance(rec, Metadata):
                    out.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    seen_footer = True
        except _DAMAGE as exc:
            out.complete = False
            out.problem = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if out.complete and not seen_footer:
            out.complete = False
            out.problem = "no footer (recording did not finish)"
    return out


@dataclass
class SalvageResult:
    messages: int = 0
    chunks: int = 0
    metadata: int = 0
    complete: bool = True  # the source had no damage
    problem: str = ""
    bytes_read: int = 0  # source bytes up to the end of the last record copied
    source_bytes: int = 0


class _SalvageCopy:
    """A source's intact records streamed into `dst`, which opens at the first message, compressed
    as asked or else as the source's first chunk."""

    def __init__(self, dst: str | Path, res: SalvageResult, compression: str | None, chunk_size: int) -> None:
        self.dst, self.res, self.compression, self.chunk_size = dst, res, compression, chunk_size
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.out_cid: dict[int, int] = {}
        self.metadata: list[Metadata] = []
        self.writer: McapWriter | None = None

    def out(self) -> McapWriter:
        if self.writer is None:
            self.writer = McapWriter(self.dst, compression=self.compression or "zstd", chunk_size=self.chunk_size)
        return self.writer

    def copy(self, f: BinaryIO) -> None:
        """Every record of `f` up to its end or its first damage; `res` says which."""
        res, seen_footer = self.res, False
        try:
            for rec in StreamReader(_Clamped(f), emit_chunks=True).records:
                if isinstance(rec, Chunk):
                    if self.compression is None:
                        self.compression = {"": "none", "lz4": "lz4", "zstd": "zstd"}.get(rec.compression, "zstd")
                    inner = breakup_chunk(rec, validate_crc=True)  # all or nothing per chunk
                    for r in inner:
                        self.take(r)
                    res.chunks += 1
                elif isinstance(rec, Footer):
                    seen_footer = True
                else:
                    self.take(rec)
                res.bytes_read = f.tell()
        except (*_DAMAGE, OSError) as exc:
            res.complete = False
            res.problem = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if res.complete and not seen_footer:
            res.complete = False
            res.problem = "no footer (recording did not finish)"

    def take(self, rec: McapRecord) -> None:
        if isinstance(rec, Schema):
            self.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self.channels[rec.id] = rec
        elif isinstance(rec, Message):
            if rec.channel_id not in self.out_cid:
                ch = self.channels[rec.channel_id]
                sc = self.schemas.get(ch.schema_id)
                self.out_cid[rec.channel_id] = self.out().register_raw(
                    ch.topic, schema_name=sc.name if sc else "", schema_encoding=sc.encoding if sc else "",
                    schema_data=sc.data if sc else b"", message_encoding=ch.message_encoding)
            self.out().write_channel(self.out_cid[rec.channel_id], rec.data, log_time_ns=rec.log_time,
                                     publish_time_ns=rec.publish_time, sequence=rec.sequence)
            self.res.messages += 1
        elif isinstance(rec, Metadata):
            self.metadata.append(rec)


def salvage(src: str | Path, dst: str | Path, *, compression: str | None = None,
            chunk_size: int = 4 * 1024 * 1024,
            extra_metadata: Callable[[SalvageResult], dict[str, dict[str, str]]] | None = None) -> SalvageResult:
    """Copy every intact record of `src` (schemas, channels, messages, metadata) into a complete `dst`.

    Streams `src` record by record and stops at the first damage (truncated or CRC-failing chunk,
    torn record): a file left by a killed writer loses at most its unfinished chunk. Compression
    defaults to that of the source's first chunk. `extra_metadata(result)` adds records at the end.
    """
    p = Path(src)
    res = SalvageResult()
    with _open(p) as f:
        _require_magic(f, p)
        res.source_bytes = p.stat().st_size
        copy = _SalvageCopy(dst, res, compression, chunk_size)
        copy.copy(f)
        w = copy.out()
        try:
            for m in copy.metadata:
                w.add_metadata(m.name, dict(m.metadata))
            res.metadata = len(copy.metadata)
            for name, data in (extra_metadata(res) if extra_metadata else {}).items():
                w.add_metadata(name, data)
        finally:
            w.close()
    return res
