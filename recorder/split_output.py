"""The recorder's MCAP output: the current file, cut into parts by size or sensor time, the
free-space checks that stop a recording while the file can still be finished, and the errors of a
failed write (recorder/writer.py: Recorder composes it).

Every file starts with the device's metadata records, the recorder's config and the camera's static
TF tree, and ends with a `recording` metadata record: this file's message counts and the
recording's counts so far, which `SplitMcapOutput` asks its owner for (`RecordingProgress`).
"""

from __future__ import annotations

import errno
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from octolog.kit.errors import DiskFull, McapError, RecorderError, WriteFailed
from octolog.kit.mcaplog import McapWriter
from octolog.recorder.capture_encoding import tf_static
from octolog.recorder.recording_types import Encoded, StreamStats

DISK_CHECK_S = 0.5  # free-space checks at most this often (and after every chunk): statvfs is not free


@dataclass(frozen=True)
class RecordingProgress:
    """The recording as a whole when a file is finished, for its `recording` metadata record."""

    stop_reason: str  # "" while recording goes on (the file is finished for a split)
    streams: dict[str, StreamStats]
    dropped_total: int
    last_stamp_ns: int
    wall_s: float


class SplitMcapOutput:
    """Owns the MCAP file being written: opens the first at the first message, a new one when the
    current is `split_size` bytes or `split_ns` of sensor time long (at a message that may start a
    file: a video capture's), and finishes the last on `finish`.

    Write errors come out as RecorderError: DiskFull (ENOSPC) or WriteFailed, naming how many
    messages were written; `check_disk` raises one when less than `min_free` bytes are free.
    """

    def __init__(self, part: Callable[[int], Path], *, compression: str, chunk_size: int, split_size: int,
                 split_ns: int, min_free: int, metadata: dict[str, dict[str, str]],
                 transforms: list[tuple[str, str, np.ndarray]], progress: Callable[[], RecordingProgress]) -> None:
        self._part = part
        self._compression = compression
        self._chunk_size = chunk_size
        self._split_size = split_size
        self._split_ns = split_ns
        self._min_free = min_free
        self._metadata = metadata  # records at the start of every file
        self._transforms = transforms
        self._progress = progress
        self._writer: McapWriter | None = None
        self._file_index = -1
        self._file_first_ns = 0
        self._file_messages: dict[str, int] = {}
        self.paths: list[Path] = []
        self.closed_messages = 0  # in finished files
        self.closed_bytes = 0
        self._next_disk_check = 0.0
        self._checked_bytes = 0
        self.free_bytes = self._disk_free()

    # --- what is written ----------------------------------------------------------------------

    @property
    def files(self) -> int:
        return self._file_index + 1

    @property
    def path(self) -> Path | None:
        """The file being written, if any."""
        w = self._writer
        return w.path if w else None

    @property
    def messages(self) -> int:
        w = self._writer
        return self.closed_messages + (w.count if w else 0)

    @property
    def flushed_messages(self) -> int:
        """Messages in chunks already on disk."""
        w = self._writer
        return self.closed_messages + (w.flushed_count if w else 0)

    @property
    def bytes_written(self) -> int:
        w = self._writer
        return self.closed_bytes + (w.size_bytes if w else 0)

    # --- writing ------------------------------------------------------------------------------

    def write(self, msgs: list[Encoded], stamp_ns: int, *, may_split: bool) -> None:
        """Append one capture's messages; first start a file if there is none, or a new one if
        `may_split` and the current one is long enough."""
        if self._writer is None or (may_split and self._want_split(stamp_ns)):
            self._rotate(stamp_ns)
        w = self._writer
        assert w is not None
        try:
            for m in msgs:
                w.write(m.topic.name, m.topic.msgtype, m.data, log_time_ns=m.stamp_ns, publish_time_ns=m.stamp_ns)
                self._file_messages[m.topic.name] = self._file_messages.get(m.topic.name, 0) + 1
        except McapError as exc:
            raise self._write_failure(exc) from None

    def _want_split(self, stamp_ns: int) -> bool:
        w = self._writer
        if w is None:
            return True
        if self._split_size and w.size_bytes >= self._split_size:
            return True
        return bool(self._split_ns and stamp_ns - self._file_first_ns >= self._split_ns)

    def _rotate(self, stamp_ns: int) -> None:
        err = self.finish()
        if err is not None:
            raise err
        self._file_index += 1
        path = self._part(self._file_index)
        try:
            w = McapWriter(path, compression=self._compression, chunk_size=self._chunk_size)
            for name, data in self._metadata.items():
                w.add_metadata(name, data)
            self._writer = w
            self._file_first_ns = stamp_ns
            self._file_messages = {}
            self.paths.append(path)
            tf = tf_static(self._transforms, stamp_ns)
            w.write(tf.topic.name, tf.topic.msgtype, tf.data, log_time_ns=stamp_ns, publish_time_ns=stamp_ns)
            self._file_messages[tf.topic.name] = 1
        except McapError as exc:
            if self._writer is None:
                raise RecorderError(str(exc)) from None
            raise self._write_failure(exc) from None

    def finish(self) -> RecorderError | None:
        """Finish the current file (its `recording` record, index, footer); the error if it could
        not be finished (it then ends where the failure left it)."""
        w = self._writer
        if w is None:
            return None
        self._writer = None
        p = self._progress()
        meta = {"file_index": str(self._file_index), "stop_reason": p.stop_reason or "split",
                "messages": json.dumps(self._file_messages, sort_keys=True),
                "streams": json.dumps({s: {k: v for k, v in vars(st).items() if k != "last_frame_number"}
                                       for s, st in p.streams.items()}, sort_keys=True),
                "dropped_total": str(p.dropped_total),
                "first_stamp_ns": str(self._file_first_ns), "last_stamp_ns": str(p.last_stamp_ns),
                "wall_s": f"{p.wall_s:.3f}"}
        err: RecorderError | None = None
        try:
            w.add_metadata("recording", meta)
        except McapError:
            pass  # after a write failure the counts are in the error message and the result
        try:
            w.close()
        except McapError as exc:
            err = RecorderError(str(exc))
        self.closed_messages += w.count
        self.closed_bytes += w.size_bytes
        return err

    # --- failures -----------------------------------------------------------------------------

    def check_disk(self) -> None:
        """Stop while there is room to finish the file, rather than at ENOSPC: raises RecorderError
        when less than `min_free` bytes are free (checked at most every DISK_CHECK_S, and after
        every chunk's worth of bytes)."""
        now = time.monotonic()
        written = self.bytes_written
        if now >= self._next_disk_check or written - self._checked_bytes >= self._chunk_size:
            self._next_disk_check = now + DISK_CHECK_S
            self._checked_bytes = written
            self.free_bytes = self._disk_free()
            if self._min_free and self.free_bytes < self._min_free:
                raise RecorderError(f"disk nearly full ({self.free_bytes / 1e6:.0f} MB free, limit "
                                    f"{self._min_free / 1e6:.0f} MB): recording stopped; "
                                    f"{self._writer.path if self._writer else ''} is complete")

    def _disk_free(self) -> int:
        try:
            return shutil.disk_usage(self._part(0).parent).free
        except OSError:
            return 0

    def _write_failure(self, exc: McapError) -> WriteFailed:
        """The error for a failed write; the recorder completes its message once it is known whether
        the file could be finished. McapWriter raises McapError from the OSError, whose errno tells
        a full disk from other I/O errors."""
        cause = exc.__context__
        full = isinstance(cause, OSError) and cause.errno == errno.ENOSPC
        kind, what = (DiskFull, "disk full") if full else (WriteFailed, f"write failed ({exc})")
        return kind(f"{what}: recording stopped after {self.messages} messages")
