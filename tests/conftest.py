import sys
from pathlib import Path

# octolog before numpy: its __init__ pins OpenBLAS's kernels for this process as for every octolog
# process, so in-process results equal the CLI's bytes (docs/architecture.md, "Determinism").
import octolog  # noqa: F401

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _free_gib() -> tuple[float, Path]:
    import shutil
    import tempfile

    base = Path(tempfile.gettempdir())
    return shutil.disk_usage(base).free / 2**30, base


_FREE_AT_START = _free_gib()


def pytest_terminal_summary(terminalreporter) -> None:
    """A full disk fails many tests at once: say so when the run began with little room."""
    free, base = _FREE_AT_START
    if free < 8:
        terminalreporter.write_line(f"disk: only {free:.1f} GiB was free under {base} when the tests began; "
                                    "the suite needs about 8 GiB", yellow=True)
