"""A session folder's state: made fresh for `octolog run`, and marked INCOMPLETE until the run succeeds."""

from __future__ import annotations

import shutil
from pathlib import Path

from octolog.kit.errors import ConfigError

# A session folder holds this file from the start of a run until its summary.json is written: a run
# that fails or is killed leaves it, with what went wrong, so no one takes the folder for a session.
INCOMPLETE = "INCOMPLETE"
# What makes a folder an octolog session (one of these is there from a run's first second).
SESSION_MARKS = ("config.toml", "metadata.json", "session.mcap", "summary.json", INCOMPLETE, "logs")


def prepare_out(out: Path, *, overwrite: bool = False) -> None:
    """Make `out` an empty folder for a new session; ConfigError naming the path if it cannot be.

    An existing session there is replaced only with `overwrite`, and then removed whole first (not
    written into a temporary folder renamed at the end: a full disk would then need room for both
    sessions, and a failed run could not leave its INCOMPLETE folder where it was asked to write).
    """
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a folder; give a folder for the session")
    parent = next((p for p in out.parents if p.exists()), None)
    if not out.exists() and parent is not None and not parent.is_dir():
        raise ConfigError(f"--out {out}: cannot make the folder: {parent} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not any((out / m).exists() for m in SESSION_MARKS):
            raise ConfigError(f"--out {out}: a folder with other files in it, not an octolog session; "
                              f"give a new or empty folder")
        if not overwrite:
            raise ConfigError(f"--out {out}: holds a session already; pass --overwrite to replace it")
        try:
            for entry in out.iterdir():  # the entries, not `out`: it may be a mount point
                shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
        except OSError as exc:
            raise ConfigError(f"--out {out}: cannot remove the old session: {exc.strerror}") from None
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / "logs").mkdir(exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot make the folder: {exc.strerror}") from None


def incomplete_reason(session: Path) -> str | None:
    """Why `session` is not a finished session (its INCOMPLETE file's text), or None if it is."""
    marker = session / INCOMPLETE
    if not marker.exists():
        return None
    try:
        text = " ".join(marker.read_text(errors="replace").split())
    except OSError as exc:
        text = f"(unreadable: {exc.strerror})"
    return text or "the run did not finish"


def not_a_session(path: Path) -> str | None:
    """Why `path` is no session folder to re-run (`octolog replay SESSION`), with the command that
    takes what it is; None when it is a folder (what it holds is checked by the replay)."""
    if path.is_dir():
        return None
    if not path.exists():
        return f"{path}: no such session folder"
    if path.name == "session.mcap" and (path.parent / "config.toml").is_file():
        return (f"{path}: a session's log, not its folder; `octolog replay {path.parent}` re-runs that "
                f"session's stages, `octolog run --source mcap:{path}` runs the pipeline on it afresh")
    return f"{path}: a file, not a session folder; `octolog run --source mcap:{path}` runs the pipeline on a recording"
