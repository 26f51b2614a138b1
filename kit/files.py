"""File output helpers shared by the stages."""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit.errors import MapError

__all__ = ["read_npz", "write_bytes_atomic", "write_npz"]


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


def write_npz(path: Path, header: dict[str, object], arrays: dict[str, np.ndarray]) -> None:
    """A NumPy `.npz` with a JSON `header.json` first, entries stored (not deflated) in the given
    order with fixed zip times, so the same content gives the same bytes; written via a temporary
    file and renamed, so a reader never sees half of it."""
    tmp = path.with_name(path.name + ".tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as z:
        _entry(z, "header.json", json.dumps(header, indent=2, sort_keys=True).encode())
        for name, value in arrays.items():
            buf = io.BytesIO()
            np.save(buf, np.ascontiguousarray(value), allow_pickle=False)
            _entry(z, f"{name}.npy", buf.getvalue())
    tmp.replace(path)


def _entry(z: zipfile.ZipFile, name: str, data: bytes) -> None:
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))  # fixed: same content, same bytes
    info.compress_type = zipfile.ZIP_STORED  # deflate saves little on floats, at ten times the time
    z.writestr(info, data)


def read_npz(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """What `write_npz` wrote: (header, arrays). Raises the zip, JSON or OS error as it comes (the
    caller names the file and what it is)."""
    with zipfile.ZipFile(path) as z:
        header = json.loads(z.read("header.json"))
        arrays = {n.removesuffix(".npy"): np.load(io.BytesIO(z.read(n)), allow_pickle=False)
                  for n in z.namelist() if n.endswith(".npy")}
    return header, arrays
