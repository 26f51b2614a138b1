"""Shared test helpers: running the real CLI, finding real data, small synthetic inputs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
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
