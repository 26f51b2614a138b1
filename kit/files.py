"""File output helpers shared by the stages."""

from __future__ import annotations

import os
from pathlib import Path

from octolog.kit.errors import MapError

__all__ = ["write_bytes_atomic"]


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write bytes to `path` via a sibling temporary file; OSError becomes a one-line MapError."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError as e:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise MapError(f"cannot write {path}: {e.strerror or e}") from None
