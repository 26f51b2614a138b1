"""A stage's known error, handed from the stage process to `octolog run` as a typed record.

`octolog run` starts each stage as a child process with `OCTOLOG_ERROR_FILE` set; when the child's
command fails with an `OctologError`, `cli.main` writes the error's type and message there, so
the orchestrator learns what went wrong without searching the child's log for the word "error".
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from octolog.kit.errors import OctologError

ENV = "OCTOLOG_ERROR_FILE"


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
    try:
        Path(path).write_text(json.dumps({"type": type(exc).__name__, "message": str(exc)}))
    except OSError:
        pass  # best effort: the error's line is in the stage's log all the same


def read(path: Path) -> ErrorRecord | None:
    """The record a stage wrote, or None if it wrote none (it succeeded, crashed or was killed)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    return ErrorRecord(str(data.get("type", "")), str(data.get("message", "")))
