"""The bundle adjustment at the end of a stream: its time and memory against the session's length.

Runs the native tracker over a synthetic room sequence (exact ground truth) once per cap on the
final BA (`tracker.global_ba_keyframes`), each in its own process so peak memory is per run, and
prints per cap: keyframes, the keyframes the final BA moved, its wall time, the process's RSS before
it and its peak (VmHWM) after, and the ATE of the final trajectory. The back end runs in-process
(`background=False`) so the peak is that of one process; results are identical either way.

    python bench/final_ba.py [--frames 600] [--fps 10] [--caps 0,150,all]

A cap of 0 is no final BA; "all" is every keyframe.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from octolog.kit import metrics
from octolog.replay.synthetic import SyntheticScene
from octolog.tracker.config import TrackerConfig
from octolog.tracker.slam import RgbdSlam

ROOT = Path(__file__).resolve().parents[1]


def _vm(key: str) -> float:
    line = next(ln for ln in Path("/proc/self/status").read_text().splitlines() if ln.startswith(key + ":"))
    return int(line.split()[1]) / 1024


def worker(frames: int, fps: float, cap: int) -> dict:
    room = SyntheticScene(n_frames=frames, fps=fps)
    odo = RgbdSlam(TrackerConfig(global_ba_keyframes=cap).odometry_params(), background=False)
    for f in room.frames():
        odo.track(f)
    odo._sync()  # the last local BA lands first, outside the timed part
    rss = _vm("VmRSS")
    peak_before = _vm("VmHWM")
    t0 = time.perf_counter()
    moved = odo.finish()
    dt = time.perf_counter() - t0
    stamps, poses = odo.trajectory()
    gt = metrics.Trajectory.from_matrices(np.array([room.stamp_ns(i) for i in range(len(room))]), room.poses())
    ate = metrics.ate(metrics.Trajectory.from_matrices(np.array(stamps), np.array(poses)), gt).rmse
    return {"keyframes": len(odo.keyframe_poses()), "moved": len(moved), "s": dt, "rss_mb": rss,
            "peak_before_mb": peak_before, "peak_mb": _vm("VmHWM"), "ate_cm": ate * 100}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600, help="synthetic frames (default 600: 3 loops at 10 fps)")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--caps", default="0,150,all", help="global_ba_keyframes values (default 0,150,all)")
    ap.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker is not None:
        print(json.dumps(worker(args.frames, args.fps, args.worker)))
        return
    caps = [10**9 if c == "all" else int(c) for c in args.caps.split(",")]
    print(f"final BA: synthetic room, {args.frames} frames at {args.fps:g} fps, native tracker, back end in-process")
    print()
    print("| global_ba_keyframes | keyframes | moved by final BA | final BA, s | RSS before, MB | peak before → after, MB "
          "| ATE, cm |")
    print("|---|---|---|---|---|---|---|")
    for cap in caps:
        out = subprocess.run([sys.executable, __file__, "--frames", str(args.frames), "--fps", str(args.fps),
                              "--worker", str(cap)], capture_output=True, text=True, check=True, cwd=ROOT)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        name = "all" if cap >= 10**9 else str(cap)
        print(f"| {name} | {r['keyframes']} | {r['moved']} | {r['s']:.1f} | {r['rss_mb']:.0f} | "
              f"{r['peak_before_mb']:.0f} → {r['peak_mb']:.0f} | {r['ate_cm']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
