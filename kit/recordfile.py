"""An output file whose writes are all-or-nothing: it always ends on the boundary of a whole write.

McapWriter writes through it, so a failed write (disk full) never leaves a torn record behind.
"""

from __future__ import annotations

import os
from pathlib import Path


def write_all(fd: int, data: bytes | memoryview) -> None:
    """os.write until done (a regular file may take a write in parts)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


class RecordFile:
    """An unbuffered output file whose writes are all-or-nothing.

    mcap's Writer hands over each record group (a whole chunk, a metadata record) in one write().
    A failed write (disk full) is cut back off the file, so the file always ends on a record
    boundary: a streaming reader reads everything before the failure, and a minimal end can
    still be written after it.
    """

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pos = 0

    def write(self, data: bytes | memoryview) -> int:
        n = len(data)
        try:
            write_all(self._fd, data)
        except OSError:
            try:
                os.ftruncate(self._fd, self._pos)
                os.lseek(self._fd, self._pos, os.SEEK_SET)
            except OSError:
                pass
            raise
        self._pos += n
        return n

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)
