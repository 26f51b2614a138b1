"""A stage's known error, handed from the stage process to `octolog run` as a typed record.

`octolog run` starts each stage as a child process with `OCTOLOG_ERROR_FILE` set; when the child's
command fails with an `OctologError`, `cli.main` writes the error's type and message there, so
the orchestrator learns what went wrong without searching the child's log for the word "error".
The orchestrator reserves the file's space before the stage starts (`reserve`), so the record can
be written on a disk the stage has just filled: the stage overwrites bytes that are already there.
Once the stage has ended, a reservation it did not use is removed (`release`): a finished session
holds `logs/STAGE.error.json` only for a stage that reported an error. The same environment tells a
stage which run it belongs to (`OCTOLOG_PARENT_PID`), so it stops when that run is killed outright
(`stop_with_parent`).
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any
from pathlib import Path

from octolog.kit.errors import OctologError

ENV = "OCTOLOG_ERROR_FILE"
REPORT_ENV = "OCTOLOG_REPORT_FILE"  # where a stage reports what it dropped (see `write_report`)
PARENT_ENV = "OCTOLOG_PARENT_PID"  # the `octolog run` a stage belongs to (see `stop_with_parent`)
RESERVED_BYTES = 8192  # a record longer than this is cut (its message: to fit)


@dataclass(frozen=True)
class ErrorRecord:
    """What a stage process reported: its error's class name (an OctologError subclass) and message."""

    type: str
    message: str


def write(exc: OctologError) -> None:
    """Record `exc` in the file `$OCTOLOG_ERROR_FILE` names, if it is set (a stage under `octolog run`)."""
    path = os.environ.get(ENV)
    if not path:
        return
    message = str(exc)
    data = json.dumps({"type": type(exc).__name__, "message": message}).encode()
    while len(data) > RESERVED_BYTES:
        message = message[: len(message) - (len(data) - RESERVED_BYTES) - 4] + "..."
        data = json.dumps({"type": type(exc).__name__, "message": message}).encode()
    try:
        # in place over the reserved bytes (no new blocks needed), then cut to length
        fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
        try:
            os.pwrite(fd, data, 0)
            os.ftruncate(fd, len(data))
        finally:
            os.close(fd)
    except OSError:
        pass  # best effort: the error's line is in the stage's log all the same


def reserve(path: Path) -> None:
    """Make `path` an empty record (no error yet) holding RESERVED_BYTES of disk space for one."""
    path.write_bytes(b" " * RESERVED_BYTES)


def release(path: Path) -> None:
    """Once the stage has ended: remove `path` unless it holds a record, so only a stage that reported
    an error leaves a file."""
    if read(path) is None:
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass  # left as it is: blanks, which `read` takes for no record


def read(path: Path) -> ErrorRecord | None:
    """The record a stage wrote, or None if it wrote none (it succeeded, crashed or was killed)."""
    try:
        data = json.loads(path.read_text())  # a reserved file (blanks only) is no JSON: no record
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    return ErrorRecord(str(data.get("type", "")), str(data.get("message", "")))


# what the stage found that its report carries besides drops and CPU (the tracker's `depth_bias`)
FINDINGS: dict[str, object] = {}


def write_report(malformed: dict[str, int], cpu: dict | None = None) -> None:
    """Record in `$OCTOLOG_REPORT_FILE` (if set) the malformed samples the stage dropped, per topic,
    where its CPU went (kit/cpuclock.py: report) and its FINDINGS."""
    path = os.environ.get(REPORT_ENV)
    if not path:
        return
    try:
        Path(path).write_text(json.dumps({"malformed": malformed, "cpu_s": cpu or {}, **FINDINGS},
                                         sort_keys=True) + "\n")
    except OSError:
        pass  # best effort: each first drop per publisher is in the stage's log


def read_cpu(path: Path) -> dict:
    """The CPU report in a stage's report file, {} if there is none."""
    return read_finding(path, "cpu_s") or {}


def read_finding(path: Path, key: str) -> Any:
    """One entry of a stage's report file (`cpu_s`, a finding), None if there is none."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data.get(key) if isinstance(data, dict) else None


def read_malformed(path: Path) -> dict[str, int]:
    """What a stage's report says it dropped (empty if it wrote none)."""
    try:
        data = json.loads(path.read_text())
        return {str(k): int(v) for k, v in data["malformed"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def stop_with_parent() -> None:
    """In a stage of `octolog run` (`$OCTOLOG_PARENT_PID` set): once that run is gone (killed outright,
    SIGKILL or out of memory, so it could not stop its stages), stop as if interrupted, finishing
    what was written, instead of running on alone for peers that went with it."""
    parent = os.environ.get(PARENT_ENV)
    if not parent or os.getppid() != int(parent):
        return

    def watch() -> None:
        while os.getppid() == int(parent):
            time.sleep(1.0)  # polling the parent's pid: no event tells a child its parent died
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="octolog-parent", daemon=True).start()
