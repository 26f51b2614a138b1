"""`octolog recover`: a complete MCAP file from one a killed or crashed recorder left behind."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from octolog.kit.errors import McapError
from octolog.kit.mcaplog import SalvageResult, salvage


@dataclass(frozen=True)
class RecoverResult:
    out: Path
    messages: int
    chunks: int
    source_complete: bool
    problem: str
    bytes_lost: int  # source bytes after the last intact record


def recover(src: Path, out: Path, *, overwrite: bool = False, compression: str | None = None) -> RecoverResult:
    """Copy every intact chunk of `src` into a new, indexed `out`, with its metadata plus a
    `recovery` record saying what was lost. At most the unfinished last chunk is."""
    src, out = Path(src), Path(out)
    if not src.is_file():
        raise McapError(f"{src}: no such MCAP file")
    if out.exists() and not overwrite:
        raise McapError(f"{out} exists; pass --overwrite to replace it")
    if out.resolve() == src.resolve():
        raise McapError(f"{out}: recover into a new file, not over the damaged one")
    tmp = out.with_name(out.name + ".part")

    def note(r: SalvageResult) -> dict[str, dict[str, str]]:
        return {"recovery": {"source": str(src), "messages": str(r.messages), "chunks": str(r.chunks),
                             "source_complete": str(r.complete).lower(), "problem": r.problem,
                             "bytes_lost": str(max(r.source_bytes - r.bytes_read, 0))}}

    try:
        res: SalvageResult = salvage(src, tmp, compression=compression, extra_metadata=note)
        if not res.complete and not (res.messages or res.metadata):
            raise McapError(f"{src}: no intact MCAP records to recover ({res.problem}); nothing written")
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    return RecoverResult(out, res.messages, res.chunks, res.complete, res.problem,
                         max(res.source_bytes - res.bytes_read, 0))
