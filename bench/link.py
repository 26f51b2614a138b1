"""Bytes over a robot's link: docs/deployment.md's robot + server, in two network namespaces.

    sudo OCTOLOG_DATA=../shared/data python bench/link.py [--source tum:PATH]

Two hosts joined by a veth pair: the server (router, `octolog map`, `octolog log`) and the robot
(replay of TUM fr1/xyz first300 + `octolog track`). Plain TCP, Zenoh's shared memory off (two
namespaces of one machine share /dev/shm, and Zenoh would pass large payloads through it; a real
link carries them). Two layouts, each run once:

- before: the robot's stages are clients of the server's router, the server logs every topic (the
  deployment docs until 2026-12-02): every frame crosses to the router and back to the tracker;
- after: the robot runs its own router joined to the server's, the server logs `--no-frames`
  into a session folder: only keyframes, poses, maps and the protocol cross.

Prints MB each way and MB per minute of camera. Needs root (ip netns).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NO_SHM = "{ transport: { shared_memory: { enabled: false } } }"


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


def start(ns: str, log: Path, *args: str) -> subprocess.Popen:
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1", "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "octolog", *args], cwd=ROOT, env=env,
                            stdout=open(log, "w"), stderr=subprocess.STDOUT)


def counters(ns: str, dev: str) -> tuple[int, int]:
    """(rx, tx) bytes of `dev` in `ns`: at the server's end, rx is robot -> server."""
    out = []
    for k in ("rx_bytes", "tx_bytes"):
        p = subprocess.run(["ip", "netns", "exec", ns, "cat", f"/sys/class/net/{dev}/statistics/{k}"],
                           capture_output=True, text=True, check=True)
        out.append(int(p.stdout))
    return out[0], out[1]


def run(layout: str, source: str, work: Path, robot_ns: str, server_ns: str, dev: str) -> tuple[int, int, float]:
    out = work / layout
    out.mkdir()
    cfg = work / "noshm.json5"
    server = ["--mode", "client", "--connect", "tcp/127.0.0.1:7447", "--zenoh-config", str(cfg), "--no-multicast",
              "--namespace", "robot1"]
    procs = {"router": start(server_ns, out / "router.log", "router", "--listen", "tcp/0.0.0.0:7447",
                             "--zenoh-config", str(cfg))}
    if layout == "after":
        procs["robot-router"] = start(robot_ns, out / "robot-router.log", "router", "--listen", "tcp/127.0.0.1:7447",
                                      "--connect", "tcp/10.77.0.2:7447", "--zenoh-config", str(cfg))
        robot_endpoint, log_args = "tcp/127.0.0.1:7447", ["--no-frames", "--out", str(out / "server-log")]
    else:
        robot_endpoint, log_args = "tcp/10.77.0.2:7447", ["--out", str(out / "server.mcap")]
    robot = ["--mode", "client", "--connect", robot_endpoint, "--zenoh-config", str(cfg), "--no-multicast",
             "--namespace", "robot1"]
    before = counters(server_ns, dev)  # everything from here counts: start-up, frames, the end
    try:
        procs["mapper"] = start(server_ns, out / "map.log", "map", *server, "--out", str(out / "map"))
        procs["log"] = start(server_ns, out / "log.log", "log", *server, *log_args)
        procs["tracker"] = start(robot_ns, out / "tracker.log", "track", *robot, "--set", "wire_compression=jpeg:90")
        t0 = time.monotonic()
        procs["replay"] = start(robot_ns, out / "replay.log", "replay", *robot, "--source", source, "--set",
                                'wait_for=["tracker", "mapper"]', "--quiet")
        for name in ("replay", "tracker", "mapper", "log"):
            if procs[name].wait(timeout=900) != 0:
                raise SystemExit(f"{layout}: {name} failed: {(out / (name if name != 'mapper' else 'map')).with_suffix('.log')}")
        wall = time.monotonic() - t0
        after = counters(server_ns, dev)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
                p.wait(timeout=30)
    return after[0] - before[0], after[1] - before[1], wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    data = os.environ.get("OCTOLOG_DATA", str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--source", default=f"tum:{data}/tum/rgbd_dataset_freiburg1_xyz_first300")
    args = ap.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("needs root (ip netns)")
    from octolog.replay.sources import open_source

    camera_s = open_source(args.source).duration_ns * 1e-9
    tag = f"lk{os.getpid() % 10000}"
    robot_ns, server_ns, dev = f"{tag}r", f"{tag}s", f"{tag}s0"
    ip("netns", "add", robot_ns)
    ip("netns", "add", server_ns)
    try:
        for ns in (robot_ns, server_ns):
            ip("-n", ns, "link", "set", "lo", "up")
        ip("link", "add", f"{tag}r0", "type", "veth", "peer", "name", dev)
        ip("link", "set", f"{tag}r0", "netns", robot_ns)
        ip("link", "set", dev, "netns", server_ns)
        ip("-n", robot_ns, "addr", "add", "10.77.0.1/24", "dev", f"{tag}r0")
        ip("-n", server_ns, "addr", "add", "10.77.0.2/24", "dev", dev)
        ip("-n", robot_ns, "link", "set", f"{tag}r0", "up")
        ip("-n", server_ns, "link", "set", dev, "up")
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            (work / "noshm.json5").write_text(NO_SHM)
            rows = {layout: run(layout, args.source, work, robot_ns, server_ns, dev) for layout in ("before", "after")}
    finally:
        ip("netns", "del", robot_ns)
        ip("netns", "del", server_ns)
    per_min = 60.0 / camera_s
    print(f"{args.source}: {camera_s:.1f} s of camera; bytes on the robot's link (server end), one run each")
    print("| layout | robot -> server MB | server -> robot MB | robot -> server MB per minute of camera | wall s |")
    print("|---|---|---|---|---|")
    for layout, (rx, tx, wall) in rows.items():
        print(f"| {layout} | {rx / 1e6:.1f} | {tx / 1e6:.1f} | {rx / 1e6 * per_min:.0f} | {wall:.1f} |")


if __name__ == "__main__":
    main()
