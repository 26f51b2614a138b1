"""The status line of a long command (`octolog run`, `demo`, `replay`, `record`, `vocab build`) on stderr.

On a terminal it is redrawn in place (`\\r`); anywhere else (a log file, a pipe, a CI job) it is a plain
line at most every `INTERVAL_S` seconds, so a log holds readable lines instead of one line of redraws.
A stage under `octolog run` writes into a pipe its orchestrator relays: the orchestrator says in
`OCTOLOG_STATUS_TTY` whether its own stderr, where the line ends up, is a terminal.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from typing import TextIO

ENV = "OCTOLOG_STATUS_TTY"  # "1": redraw in place, "0": plain lines; unset: whether stderr is a terminal
INTERVAL_S = 5.0  # plain lines: at most one this often (the last one always comes, at `end`)

_latest: StatusLine | None = None  # the line shown last in this process (`end_latest`)


def is_terminal(stream: TextIO) -> bool:
    """Whether `stream` shows a redrawn line as one line: `OCTOLOG_STATUS_TTY` if set, else isatty."""
    given = os.environ.get(ENV)
    if given in ("0", "1"):
        return given == "1"
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class StatusLine:
    """One command's status line: `show` each new state, `end` once done (or before another line)."""

    def __init__(self, stream: TextIO | None = None, *, tty: bool | None = None, interval_s: float = INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = is_terminal(self.stream) if tty is None else tty
        self.interval_s = interval_s
        self.clock = clock
        self.open = False  # a redrawn line is on the terminal without its newline yet
        self._width = 0  # the open line's length: a shorter one is padded to cover it
        self._last: float | None = None  # when the last plain line went out
        self._pending: str | None = None  # a plain line held back by the interval

    def show(self, text: str) -> None:
        """The newest state: redrawn at once on a terminal; elsewhere written if the interval has passed."""
        global _latest
        _latest = self
        if self.tty:
            self.stream.write("\r" + text + " " * max(0, self._width - len(text)))
            self._width, self.open = len(text), True
        else:
            now = self.clock()
            if self._last is not None and now - self._last < self.interval_s:
                self._pending = text
                return
            self.stream.write(text + "\n")
            self._last, self._pending = now, None
        self.stream.flush()

    def end(self) -> None:
        """Finish the line: end an open redrawn line, or write the last state the interval held back."""
        if self.open:
            self.stream.write("\n")
        elif self._pending is not None:
            self.stream.write(self._pending + "\n")
        else:
            return
        self.open, self._width, self._pending = False, 0, None
        self.stream.flush()


def end_latest() -> None:
    """End the status line this process showed last, if any: before an error line, which then starts
    a line of its own."""
    if _latest is not None:
        _latest.end()
