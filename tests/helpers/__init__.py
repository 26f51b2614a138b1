"""Shared test helpers: running the real CLI, finding real data, small synthetic inputs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TUM_NAME = "rgbd_dataset_freiburg1_xyz_first300"


def octolog(*args: str, timeout: float = 600, check: bool = True, env: dict[str, str] | None = None,
            **kw) -> subprocess.CompletedProcess:
    """Run `python -m octolog ARGS` as a subprocess, as a user would (`env`: added to the environment)."""
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1", **(env or {})}
    proc = subprocess.run([sys.executable, "-m", "octolog", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT, **kw)
    if check and proc.returncode != 0:
        raise AssertionError(f"octolog {' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


def rerun_cli() -> str:
    return str(Path(sys.executable).with_name("rerun"))


def tum_first300() -> Path:
    """The TUM fr1/xyz first-300 folder, or skip: it lives in ../shared, never in the repo."""
    root = os.environ.get("OCTOLOG_DATA")
    if not root:
        pytest.skip("real data: set OCTOLOG_DATA to the shared data folder (holding tum/...)")
    folder = Path(root) / "tum" / TUM_NAME
    if not (folder / "rgb.txt").is_file():
        pytest.skip(f"real data: {folder} not found")
    return folder


def read_until(proc: subprocess.Popen, text: str) -> str:
    """Read a text-mode process's stdout until `text` appears (blocking reads: the output is the
    event, nothing sleeps); what was read. Fails if the process ends first."""
    seen = ""
    while text not in seen:
        ch = proc.stdout.read(1)
        assert ch, seen
        seen += ch
    return seen


def kill_then_finish(procs: dict[str, subprocess.Popen], kill: tuple[str, ...], finish: tuple[str, ...],
                     logs: Path) -> None:
    """SIGKILL the processes `kill`, then wait for `finish` to exit 0 (their logs in `logs`); in
    any case leave no process behind."""
    try:
        for name in kill:
            procs[name].kill()
            procs[name].wait(timeout=30)
        for name in finish:
            assert procs[name].wait(timeout=600) == 0, (name, (logs / f"{name}.log").read_text())
    finally:
        stop_all(procs)


def stop_all(procs: dict[str, subprocess.Popen]) -> None:
    """Terminate whatever of `procs` is still running, and wait for it: no process left behind."""
    for p in procs.values():
        if p.poll() is None:
            p.terminate()
            p.wait(timeout=30)


def free_port() -> int:
    """A loopback TCP port nobody holds now (the OS picks it)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def random_frame(seq: int = 0, w: int = 16, h: int = 12, *, stamp_ns: int | None = None, depth_scale_m: float = 0.001,
                 intrinsics=None):
    """A small RgbdFrame of colour and depth (1..3999 units) drawn from a generator seeded with `seq`:
    input for codec, wire and hostile-input tests, where the picture's content does not matter
    (`intrinsics`: default a pinhole of 9 px focal length, centred)."""
    import numpy as np

    from octolog.kit.geometry import Intrinsics, RgbdFrame

    rng = np.random.default_rng(seq)
    return RgbdFrame(seq, 1000 + seq if stamp_ns is None else stamp_ns, rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
                     rng.integers(1, 4000, (h, w), dtype=np.uint16), depth_scale_m,
                     intrinsics or Intrinsics(w, h, 9.0, 9.0, w / 2, h / 2))
