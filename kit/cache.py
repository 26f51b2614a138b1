"""octolog's cache folder: data that is slow to compute, exactly reproducible, and safe to delete.

`$OCTOLOG_CACHE`, else `$XDG_CACHE_HOME/octolog`, else `~/.cache/octolog`; each user of it keeps a
folder of its own there (`cache_root("simcamera")`). Whatever is cached is keyed by a hash of
everything that decides its bytes, so a cached result is the computed one; `store_arrays` and
`load_arrays` keep numpy arrays that way, and a cache that cannot be written (read-only, full disk)
only costs the time of computing again.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import zipfile
from collections.abc import Iterable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

CACHE_ENV = "OCTOLOG_CACHE"


def cache_root(name: str) -> Path:
    """The folder `name` keeps its cached data in (not created here)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]) / name
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "octolog" / name


def key_of(parts: Iterable[object], files: Iterable[str | Path] = (), libraries: Iterable[str] = ()) -> str:
    """A hash of `parts` (their repr), the bytes of `files` (the source that computes the result)
    and the installed versions of `libraries`: what decides a cached result's bytes."""
    h = hashlib.sha256()
    for part in parts:
        h.update(repr(part).encode())
    for file in files:
        h.update(Path(file).read_bytes())
    for lib in libraries:
        try:
            h.update(f"{lib}={version(lib)}".encode())
        except PackageNotFoundError:  # not installed under that name: part of the key all the same
            h.update(f"{lib}=unknown".encode())
    return h.hexdigest()[:24]


def load_arrays(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays `store_arrays` kept at `path` (None when there are none, or they cannot be read)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):  # missing, truncated, not an npz: computed again
        return None


def store_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Keep `arrays` at `path`: written to a temporary name and renamed, so a reader never sees part
    of a file; a cache that cannot be written is left as it is."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".part")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError:
        pass
