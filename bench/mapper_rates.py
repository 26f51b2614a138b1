"""A mapper process fed a session's keyframes faster and faster, until it falls behind.

For each rate R, on a router of its own: `octolog map` (default config: 5 cm with free space and
colour, the dense cloud, the grid and snapshots every 10 keyframes), and `octolog replay --source
mcap:SESSION/session.mcap --set play=tracker --set rate=R`, which publishes the session's logged
keyframes and corrections at their sensor stamps, R times faster than the camera made them. This
process listens to the mapper's `mapper/update` (one per keyframe integrated). A keyframe's lag is
when its update came, against when it was due (its stamp, played R times faster), less the
smallest such difference (the keyframe served soonest). A mapper that keeps up ends with a lag of
about one keyframe's cost; one that falls behind ends with a lag that grew with every keyframe
(here: more than 0.5 s).

    python bench/mapper_rates.py SESSION [--rates 1,2,4,8,16]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

from octolog.kit.bus import Bus, BusConfig
from octolog.schemas import codec
from octolog.schemas.topics import MAP_UPDATE


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one_rate(log: Path, rate: float, out: Path, mapper_sets: list[str]) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1"}
    octolog = [sys.executable, "-m", "octolog"]
    bus = ["--mode", "client", "--connect", endpoint, "--no-multicast"]
    procs = [subprocess.Popen([*octolog, "router", "--listen", endpoint], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)]
    try:
        while "listening" not in procs[0].stdout.readline():
            pass
        updates = []
        with Bus(BusConfig(mode="client", connect=(endpoint,), multicast_scouting=False), "probe") as probe:
            probe.start([MAP_UPDATE])
            mapper = subprocess.Popen([*octolog, "map", *bus, "--rerun", "off", "--out", str(out), *mapper_sets], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
            procs.append(mapper)
            procs.append(subprocess.Popen([*octolog, "replay", *bus, "--quiet", "--source", f"mcap:{log}",
                                           "--set", "play=tracker", "--set", f"rate={rate}",
                                           "--set", 'wait_for=["mapper"]'], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT))
            while mapper.poll() is None:
                r = probe.receive(timeout_s=0.5)
                if r is not None:
                    msg = r.decode()
                    updates.append((time.monotonic(), codec.stamp_ns(msg.header), float(msg.processing_ms)))
            while (r := probe.receive_nowait()) is not None:
                msg = r.decode()
                updates.append((time.monotonic(), codec.stamp_ns(msg.header), float(msg.processing_ms)))
        for p in procs[1:]:
            p.wait(timeout=600)
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(timeout=30)
    arrived = np.array([u[0] for u in updates])
    stamps = np.array([u[1] for u in updates], dtype=np.float64)
    lag = arrived - (stamps - stamps[0]) * 1e-9 / rate
    lag -= lag.min()  # the clock: the keyframe served soonest after it was due
    span_s = (stamps[-1] - stamps[0]) * 1e-9 / rate
    stats = json.loads((out / "map_stats.json").read_text())
    return {"keyframes": len(updates), "offered": (len(updates) - 1) / span_s if span_s > 0 else float("inf"),
            "ms": float(np.median([u[2] for u in updates])), "lag_end": float(lag[-1]),
            "lag_median": float(np.median(lag)), "voxels": stats["occupied_voxels"] + stats["free_voxels"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("--rates", default="1,2,4,8,16")
    args = ap.parse_args()
    log = args.session / "session.mcap"
    # the session's map frame, as `octolog run` gave its mapper (no camera here to ask for gravity)
    up = tomllib.loads((args.session / "config.toml").read_text()).get("mapper", {}).get("grid_up")
    mapper_sets = ["--set", f"grid_up={json.dumps(up)}"] if up else []
    tmp = Path(tempfile.mkdtemp(prefix="octolog-rates-"))
    print(f"{args.session}: its logged keyframes into a mapper process, played faster than the camera")
    print("| rate | keyframes | offered, keyframes/s | mapper ms per keyframe, median | lag at the end, s | "
          "median lag, s | keeps up |")
    print("|---|---|---|---|---|---|---|")
    for rate in (float(r) for r in args.rates.split(",")):
        r = one_rate(log, rate, tmp / f"r{rate:g}", mapper_sets)
        keeps = r["lag_end"] < 0.5
        print(f"| {rate:g}× | {r['keyframes']} | {r['offered']:.1f} | {r['ms']:.1f} | {r['lag_end']:.2f} | "
              f"{r['lag_median']:.2f} | {'yes' if keeps else 'no'} |", flush=True)


if __name__ == "__main__":
    main()
