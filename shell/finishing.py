"""What `octolog run` says between the frames' source's end and the last stage's exit."""

from __future__ import annotations

import time
from collections.abc import Callable

from octolog.shell import statusline
from octolog.shell.children import StageProcesses


class Finishing:
    """What `octolog run` says once the frames' source has ended and other stages still work: a log
    or terminal is not silent through the tracker's last adjustment and the map's files (seconds,
    more on a busy machine): a line when the source ends, then one every `statusline.INTERVAL_S`."""

    WORK = (("tracker", "the tracker's last adjustment"), ("mapper", "the map and its files"))

    def __init__(self, children: StageProcesses, *, live: bool, quiet: bool,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.children, self.live, self.quiet, self.clock = children, live, quiet, clock
        self.since: float | None = None  # when the source ended
        self._said = 0.0  # when the last line went out

    def done(self, stage: str, running: list[str]) -> None:
        """A stage finished without error (`StageProcesses.wait_all`)."""
        left = self._left(running)
        if stage in ("recorder", "replay") and not self.quiet and left:
            what = "the camera stopped" if self.live else "the replay sent its last frame"
            self.children.say(f"octolog run: {what}; finishing {left}")
            self.since = self._said = self.clock()

    def waiting(self, running: list[str]) -> None:
        """Stages still run (`StageProcesses.wait_all`, every poll): after the source's end, a line
        every few seconds with what is left."""
        if self.since is None or not (left := self._left(running)):
            return
        now = self.clock()
        if now - self._said >= statusline.INTERVAL_S:
            self.children.say(f"octolog run: still finishing {left} ({now - self.since:.0f} s since the "
                              f"{'camera stopped' if self.live else 'last frame'})")
            self._said = now

    @classmethod
    def _left(cls, running: list[str]) -> str:
        return " and ".join(work for name, work in cls.WORK if name in running)
