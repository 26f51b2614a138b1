"""One base exception for every error octolog knows how to explain in one line."""

from __future__ import annotations


class OctologError(Exception):
    """A known error: the CLI prints its message on one line and exits 1."""


class ConfigError(OctologError):
    """An invalid configuration key or value."""


class InputError(OctologError):
    """Unreadable or malformed input data (dataset folders, images, files)."""


class McapError(InputError):
    """An MCAP file that cannot be read or written."""


class BusError(OctologError):
    """A Zenoh session or transport problem."""


class VizError(OctologError):
    """A Rerun recording that cannot be written or sent."""


class StageError(OctologError):
    """A pipeline stage failed or a peer stage disappeared."""


class TrackingError(OctologError):
    """The tracker cannot run on the given input."""


class MapError(OctologError):
    """The mapper cannot integrate its input or write its outputs."""


class RecorderError(OctologError):
    """The camera or the recording cannot go on (no device, bad profile, disk full, ...)."""


class DeviceLost(RecorderError):
    """The camera went away mid-recording (unplugged, powered off, USB reset)."""


class WriteFailed(RecorderError):
    """Writing the recording failed mid-way (I/O error); the file keeps everything before it."""


class DiskFull(WriteFailed):
    """The disk filled up (ENOSPC) mid-recording or mid-run."""


class StageFailed(StageError):
    """A stage process of `octolog run` ended badly; `stage` names it, `log` is its log file.

    `reason` is the stage's own account: its known error's message when it reported one, else the
    last line of its log (a traceback's last line, or whatever it printed before it died).
    """

    def __init__(self, stage: str, how: str, reason: str, log: str) -> None:
        super().__init__(f"the {stage} stage {how}: {reason} (log: {log})")
        self.stage, self.reason, self.log = stage, reason, log


class StageKilled(StageFailed):
    """A stage process was killed by a signal (OOM killer, kill -9, ...), not asked to stop."""

    def __init__(self, stage: str, signal: int, reason: str, log: str) -> None:
        super().__init__(stage, f"killed by signal {signal}", reason, log)
        self.signal = signal


class StageExited(StageFailed):
    """A stage process exited with a non-zero code (its own error: bad input, config, transport)."""

    def __init__(self, stage: str, code: int, reason: str, log: str) -> None:
        super().__init__(stage, f"exited with code {code}", reason, log)
        self.code = code
