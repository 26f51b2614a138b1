"""Several robots through the real processes: a router, a mapper for robots r1 and r2, and per robot a
replay and a tracker, each its own process under its robot's namespace, on two halves of the
synthetic sequence (r2's half shifted in time to run alongside r1's)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from helpers import ROOT, free_port, stop_all

FRAMES = 40
HALF = FRAMES // 2
SHIFT_S = (0.0, -0.65)  # replay.time_shift_s per robot: r2's half starts 17 ms after r1's
ROBOTS = ("r1", "r2")


def spawn(log: Path | None, *args: str) -> subprocess.Popen:
    """`python -m octolog ARGS` started, its output (unbuffered) into the file `log`, else a pipe."""
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1", "PYTHONUNBUFFERED": "1", "PYTHONHASHSEED": "0"}
    return subprocess.Popen([sys.executable, "-m", "octolog", *args], cwd=ROOT, env=env, text=True,
                            stdout=open(log, "w") if log else subprocess.PIPE, stderr=subprocess.STDOUT)


def start_router(out: Path) -> tuple[dict[str, subprocess.Popen], list[str]]:
    """`out` made, a router started on a free loopback port: the processes so far and the bus flags
    that reach it."""
    out.mkdir(parents=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    return {"router": spawn(out / "router.log", "router", "--listen", endpoint)}, \
        ["--mode", "client", "--connect", endpoint, "--no-multicast"]


def run_fleet(out: Path, start_poses: list[list[float]], *, rerun: str = "off", source: str = f"synthetic:{FRAMES}",
              windows: tuple[tuple[int, int], ...] = ((0, HALF), (HALF, FRAMES)),
              shifts: tuple[float, ...] = SHIFT_S, sources: tuple[str, ...] = (),
              mapper_sets: tuple[str, ...] = (), replay_sets: tuple[str, ...] = ()) -> dict[str, str]:
    """Router, mapper for r1+r2, and per robot a tracker and a replay: six processes over Zenoh
    (`sources`: one per robot, else `source` for both)."""
    procs, bus = start_router(out)
    try:
        poses = "[" + ", ".join("[" + ", ".join(repr(x) for x in p) + "]" for p in start_poses) + "]"
        procs["mapper"] = spawn(out / "mapper.log", "map", *bus, "--out", str(out), "--rerun", rerun,
                                "--recording-id", "fleet", "--set", 'robots=["r1", "r2"]',
                                "--set", f"start_poses={poses}", *(a for s in mapper_sets for a in ("--set", s)))
        for robot, (start, end), shift, src in zip(ROBOTS, windows, shifts, sources or (source, source)):
            ns = ["--namespace", robot]
            procs[f"tracker-{robot}"] = spawn(out / f"tracker-{robot}.log", "track", *bus, *ns)
            procs[f"replay-{robot}"] = spawn(out / f"replay-{robot}.log", "replay", *bus, *ns, "--quiet",
                                             "--source", src, "--set", f"start={start}", "--set", f"end={end}",
                                             "--set", f"time_shift_s={shift!r}",
                                             "--set", 'wait_for=["tracker", "mapper"]',
                                             *(a for s in replay_sets for a in ("--set", s)))
        for name in ("replay-r1", "replay-r2", "tracker-r1", "tracker-r2", "mapper"):
            code = procs[name].wait(timeout=600)
            assert code == 0, (name, (out / f"{name}.log").read_text())
    finally:
        stop_all(procs)
    return {name: (out / f"{name}.log").read_text() for name in procs}
