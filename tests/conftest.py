"""Fixtures every test module may use: loopback ports, small frames, the shared end-to-end runs.

Markers (registered in pyproject.toml): `slow` for tests that run the real processes over a whole
sequence or a matrix of them, `root` for those that need root (network namespaces, a tmpfs mount).
`make test-quick` runs the rest; `make test` and CI run everything.
"""

import sys
from collections.abc import Callable
from pathlib import Path

# octolog before numpy: its __init__ pins OpenBLAS's kernels for this process as for every octolog
# process, so in-process results equal the CLI's bytes (docs/architecture.md, "Determinism").
import octolog  # noqa: F401

# the shared helpers (tests/helpers/) import as `helpers` in every test module; test modules import
# nothing from one another
sys.path.insert(0, str(Path(__file__).resolve().parent))

import pytest  # noqa: E402
from helpers import free_port, tum_first300  # noqa: E402
from helpers import octolog as octolog_cli  # noqa: E402


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


@pytest.fixture
def endpoint() -> str:
    """A Zenoh TCP endpoint on a loopback port nobody holds now."""
    return f"tcp/127.0.0.1:{free_port()}"


RunFn = Callable[..., tuple[Path, str]]


@pytest.fixture(scope="session")
def octolog_run(tmp_path_factory) -> RunFn:
    """`octolog run --source SOURCE --quiet --rerun off ARGS...` made once per distinct call in a test
    run and shared: the end-to-end runs that several modules read (first300, the synthetic room) cost
    one run each, also across pytest-xdist workers (the first to ask makes it, under a file lock, the
    others wait for it and read it). Returns (output folder, stdout). The folder is read-only for its
    readers: a test that changes a run's files makes its own run."""
    import fcntl
    import hashlib
    import os

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base

    def run(source: str, *args: str) -> tuple[Path, str]:
        key = hashlib.sha256(repr((source, args)).encode()).hexdigest()[:16]
        folder = shared / f"shared-run-{key}"
        folder.mkdir(exist_ok=True)
        out, said = folder / "out", folder / "stdout.txt"
        with open(folder / "lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not said.exists():
                proc = octolog_cli("run", "--source", source, "--out", str(out), "--overwrite", "--quiet", "--rerun", "off",
                                   *args)
                said.write_text(proc.stdout)
        return out, said.read_text()

    return run


@pytest.fixture(scope="session")
def first300_run(octolog_run: RunFn) -> tuple[Path, str]:
    """The whole pipeline on TUM fr1/xyz first300 with the default config (skips without the data)."""
    return octolog_run(f"tum:{tum_first300()}")


# Seconds of wall time per module in a whole `make test` (three workers on two cores; pytest
# --durations=0, summed per module), for the modules above 15 s: they start longest first, the rest
# follow, those with more `slow` tests sooner. Only the schedule depends on it; re-measure when a
# module's time moves a lot.
MODULE_SECONDS = {
    "test_tour": 192, "test_distributed": 190, "test_slam": 173, "test_fleet": 171, "test_prior_map": 151,
    "test_determinism": 117, "test_depth_noise": 111, "test_recorder": 94, "test_pipeline": 82, "test_imu": 77,
    "test_wire": 69, "test_relink": 58, "test_failures": 48, "test_importers": 48,
    "test_gravity": 36, "test_hostile": 35, "test_tls": 35, "test_odometry": 27, "test_fleet_order": 23,
    "test_live": 23, "test_sessions": 23, "test_simcamera": 22, "test_viz": 21, "test_orbslam3": 20,
    "test_voxelmap": 19, "test_shards": 17, "test_journal": 17, "test_map_accuracy": 15,
}


def pytest_configure(config) -> None:
    """pytest-xdist (3.x) hands out `--dist loadfile`'s modules by their number of tests unless told
    not to: keep the collection order, longest first (pytest_collection_modifyitems)."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items) -> None:
    """pytest-xdist hands whole modules to its workers in collection order: the long ones start early,
    so no worker is left with one at the end while the other idles."""
    slow: dict[str, int] = {}
    for item in items:
        slow[item.module.__name__] = slow.get(item.module.__name__, 0) + (item.get_closest_marker("slow") is not None)

    def rank(item) -> tuple[int, int]:
        name = item.module.__name__
        return (-MODULE_SECONDS.get(name, 0), -slow[name])

    items.sort(key=rank)  # stable: a module's tests keep their order


@pytest.fixture(scope="session", autouse=True)
def _cache(tmp_path_factory) -> None:
    """octolog's cache (octolog.kit.cache: the synthetic room's textures, the simulated D455's
    rendered frames) goes under the test run's base folder, shared by the xdist workers, never into
    the user's ~/.cache."""
    import os

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    os.environ.setdefault("OCTOLOG_CACHE", str(shared / "cache"))
