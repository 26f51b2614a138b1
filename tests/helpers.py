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
