"""Logging for one process: plain lines on stderr, each naming its stage, at the level the CLI asks.

Library modules log through `logging.getLogger(__name__)` and never print; the CLI calls
`configured(stage, level)` once around a command. `octolog run` sends each stage's stderr into
`logs/<stage>.log`, so a line reads the same in a terminal and in a file:

    2026-01-31T12:00:00.250Z tracker WARNING octolog.tracker.node: tracker.rolling_shutter_ms = ...

Native libraries log on the same stderr through Rust's `tracing` (Rerun's warnings, Zenoh's with
`RUST_LOG`), which colours its lines with ANSI codes unless `NO_COLOR` is set: where stderr is not a
terminal (a log file, a pipe), `configured` sets it, so those lines are plain text too.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Iterator
from typing import TextIO

LEVELS = ("debug", "info", "warning", "error")
DEFAULT_LEVEL = "warning"
FORMAT = "%(asctime)s %(stage)s %(levelname)s %(name)s: %(message)s"

_level = DEFAULT_LEVEL  # the level `configured` set, which `octolog run` hands to its stages


class StageFormatter(logging.Formatter):
    """`FORMAT` with UTC times to the millisecond (as Rerun's and Zenoh's lines have them), no colour."""

    converter = time.gmtime
    default_time_format = "%Y-%m-%dT%H:%M:%S"
    default_msec_format = "%s.%03dZ"

    def __init__(self) -> None:
        super().__init__(FORMAT)


class _StageFilter(logging.Filter):
    """Puts the process's stage into each record that does not name one (`extra={"stage": ...}` does)."""

    def __init__(self, stage: str) -> None:
        super().__init__()
        self.stage = stage

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "stage"):
            record.stage = self.stage
        return True


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever `sys.stderr` is when a record comes (a test's capture may have replaced it)."""

    def __init__(self) -> None:
        logging.Handler.__init__(self)

    @property  # type: ignore[override]
    def stream(self) -> TextIO:
        return sys.stderr


def stage_handler(stage: str, stream: TextIO | None = None) -> logging.Handler:
    """A handler writing plain `FORMAT` lines naming `stage`, to `stream` (default: stderr)."""
    handler: logging.Handler = logging.StreamHandler(stream) if stream is not None else _StderrHandler()
    handler.setFormatter(StageFormatter())
    handler.addFilter(_StageFilter(stage))
    return handler


def level() -> str:
    """The level this process logs at (`configured`'s, else the default)."""
    return _level


@contextlib.contextmanager
def configured(stage: str, level: str = DEFAULT_LEVEL, *, stream: TextIO | None = None) -> Iterator[logging.Handler]:
    """Log octolog's records at `level` and up (one of LEVELS), other libraries' from warning up, as
    plain lines naming `stage` on `stream` (default: stderr); undone when the block ends."""
    global _level
    if level not in LEVELS:
        raise ValueError(f"log level {level!r}: want one of {', '.join(LEVELS)}")
    out = stream if stream is not None else sys.stderr
    if not _is_terminal(out):
        os.environ.setdefault("NO_COLOR", "1")  # read by Rust's tracing when Rerun or Zenoh start logging
    root, ours = logging.getLogger(), logging.getLogger("octolog")
    saved = (root.level, ours.level, _level)
    numeric = getattr(logging, level.upper())
    handler = stage_handler(stage, stream)
    root.addHandler(handler)
    root.setLevel(max(numeric, logging.WARNING))
    ours.setLevel(numeric)
    _level = level
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        root.setLevel(saved[0])
        ours.setLevel(saved[1])
        _level = saved[2]


def _is_terminal(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
