"""A live session on the simulated D455: frames skipped, and outputs against the recording.

    python bench/live.py [--seconds 30] [--fps 15 30]

`octolog run --source d455:software --duration S` at 640x480 colour and depth, paced at the
profile's rate (pyrealsense2's software device, as a camera would deliver), default outputs
(session log and Rerun recordings on). The recorder writes `recording.mcap` (what `octolog record`
alone writes for the same frames) beside the session; the session's own outputs are `session.mcap`
and the `.rrd` files. Prints one row per frame rate: frames the camera delivered / published /
consumed / skipped (the tracker keeps up by skipping, each skip on record; the camera holds back a
frame while the tracker has two in hand and lags more than tracker.live_lag_ms; how many in the first
STARTUP_S seconds, while every stage still warms up), and the outputs' size against the recording's.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from octolog.replay.sources import consumed_frames

ROOT = Path(__file__).resolve().parents[1]
STARTUP_S = 2.0  # skipped frames in the session's first seconds are counted apart: start-up, not steady state


def run(seconds: float, fps: int, out: Path) -> dict:
    vga = ["recorder.color.width=640", "recorder.color.height=480", "recorder.depth.width=640",
           "recorder.depth.height=480", f"recorder.color.fps={fps}", f"recorder.depth.fps={fps}"]
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "octolog", "run", "--source", "d455:software", "--duration", str(seconds),
                    "--out", str(out), "--quiet", *[a for s in vga for a in ("--set", s)]],
                   check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    wall = time.monotonic() - t0
    frames = json.loads((out / "summary.json").read_text())["frames"]
    # skipped frames by when: the camera's frames are numbered from 0, the tracker's statuses say which it took
    consumed = consumed_frames(out / "session.mcap")
    early = sum(1 for seq in range(int(STARTUP_S * fps)) if seq not in consumed)
    outputs = (out / "session.mcap").stat().st_size + sum(p.stat().st_size for p in (out / "rerun").glob("*.rrd"))
    return {"fps": fps, **frames, "early": early, "recording_mb": (out / "recording.mcap").stat().st_size / 1e6,
            "outputs_mb": outputs / 1e6, "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--fps", type=int, nargs="+", default=[15, 30])
    ap.add_argument("--repeat", type=int, default=1, help="runs per frame rate, one row each")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for fps in args.fps:
            for i in range(args.repeat):
                rows.append(run(args.seconds, fps, Path(tmp) / f"live{fps}-{i}"))
    print(f"d455:software, 640x480 colour + depth, {args.seconds:g} s, default outputs; {args.repeat} run(s) each")
    print(f"| fps | camera | published | consumed | skipped (of them held back; in the first {STARTUP_S:g} s) "
          "| recording.mcap MB "
          "| session.mcap + .rrd MB | outputs / recording | wall s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['fps']} | {r['camera']} | {r['published']} | {r['consumed']} | {r['skipped']} "
              f"({r['skipped'] / max(r['camera'], 1):.0%}; {r['held_back']}; {r['early']}) "
              f"| {r['recording_mb']:.1f} | {r['outputs_mb']:.1f} | {r['outputs_mb'] / r['recording_mb']:.2f} "
              f"| {r['wall_s']:.1f} |")


if __name__ == "__main__":
    main()
