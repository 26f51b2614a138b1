"""Long-session pipeline benchmark: the synthetic room looped for minutes through `octolog run`.

Does the whole pipeline's cost grow with the session? One loop around the pillar (18 s, 540 frames,
the periodic synthetic path) is rendered once into an MCAP of compressed frames (PNG, as a session
log holds them; the renderer runs in a child process), with the ground truth of every loop in its
metadata. `octolog run --source mcap:LOOP --set replay.loop=N` then plays it for `--minutes` (default
10: 18,000 frames at 30 fps) with its default outputs (session log, Rerun recordings), in lockstep.
While it runs, every stage's memory (VmRSS of each process, the tracker's worker included) and the
size of the outputs are sampled; afterwards the session log gives the tracker's time per frame and
the mapper's per keyframe, per minute of sensor time.

    python bench/long_pipeline.py [--minutes 10] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from scipy.stats import theilslopes

from long_session import FPS, loop_poses  # noqa: E402  (bench/ is this script's folder)
from pipeline import pct  # noqa: E402

from octolog.kit.mcaplog import McapWriter, read_wire
from octolog.kit.metrics import format_tum
from octolog.replay.synthetic_trajectory import LOOP_S
from octolog.schemas import codec, rgbdmsgs, topics, wirecompression

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("replay", "track", "map", "log")


def render_loop_mcap(path: Path, n_loop: int, loops: int) -> None:
    """One loop as compressed frames in an MCAP, the ground truth of `loops` loops in its metadata."""
    import cv2

    from octolog.kit.geometry import EncodedRgbd
    from octolog.replay.synthetic import SyntheticScene

    scene = SyntheticScene(n_frames=n_loop)
    poses = loop_poses(n_loop)
    period_ns = round(n_loop * 1e9 / FPS)
    with McapWriter(path, compression="lz4") as mcap:
        stamps = [scene.config.start_ns + round(k * 1e9 / FPS) for k in range(n_loop)]
        all_stamps = np.array([s + i * period_ns for i in range(loops) for s in stamps])
        mcap.add_metadata("groundtruth", {"tum": format_tum(all_stamps, np.concatenate([poses] * loops))})
        for k, T in enumerate(poses):
            rgb, depth = scene.render_pose(T)
            colour = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1])[1]
            dpng = cv2.imencode(".png", depth, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1]
            frame = EncodedRgbd(k, stamps[k], colour.tobytes(), "rgb8; png compressed bgr8", dpng.tobytes(),
                                wirecompression.DEPTH_PNG_FORMAT, scene.depth_scale_m, scene.intrinsics)
            data = codec.encode(rgbdmsgs.encoded_rgbd_msg(frame), topics.RGBD_COMPRESSED.msgtype)
            mcap.write(topics.RGBD_COMPRESSED.name, topics.RGBD_COMPRESSED.msgtype, data, log_time_ns=stamps[k],
                       publish_time_ns=stamps[k])


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _stage(pid: int) -> str:
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return ""
    for a in argv:
        if a.decode(errors="replace") in STAGES:
            return a.decode()
    return "worker"  # the tracker's back-end worker (a child of the tracker)


def sample(run_pid: int, out: Path, stop: threading.Event, rows: list[dict], every_s: float = 5.0) -> None:
    t0 = time.monotonic()
    while not stop.wait(every_s):
        mem: dict[str, float] = {"run": _rss_mb(run_pid)}
        for child in _children(run_pid):
            mem[_stage(child)] = _rss_mb(child)
            for grandchild in _children(child):
                mem["worker"] = _rss_mb(grandchild)
        size = sum(p.stat().st_size for p in [out / "session.mcap", *(out / "rerun").glob("*.rrd")] if p.exists())
        rows.append({"t": time.monotonic() - t0, "mem": mem, "bytes": size})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--keep", help="copy the session folder here (its slam_map.npz: bench/mapfile.py)")
    args = ap.parse_args()
    n_loop = round(LOOP_S * FPS)
    loops = max(1, round(args.minutes * 60 / LOOP_S))
    with tempfile.TemporaryDirectory(prefix="octolog-longpipe-") as tmp:
        loop = Path(tmp) / "loop.mcap"
        t0 = time.monotonic()
        subprocess.run([sys.executable, __file__, "--render-to", str(loop), "--loops", str(loops)], check=True)
        print(f"rendered one loop ({n_loop} frames) in {time.monotonic() - t0:.0f} s; playing it {loops} times "
              f"({loops * n_loop} frames) through octolog run", flush=True)
        out = Path(tmp) / "session"
        t0 = time.monotonic()
        proc = subprocess.Popen([sys.executable, "-m", "octolog", "run", "--source", f"mcap:{loop}", "--out", str(out),
                                 "--quiet", "--set", f"replay.loop={loops}"], cwd=ROOT, stdout=subprocess.PIPE, text=True)
        rows: list[dict] = []
        stop = threading.Event()
        sampler = threading.Thread(target=sample, args=(proc.pid, out, stop, rows), daemon=True)
        sampler.start()
        summary_text = proc.communicate()[0]
        stop.set()
        sampler.join()
        wall = time.monotonic() - t0
        if proc.returncode:
            kept = Path(tempfile.mkdtemp(prefix="octolog-longpipe-failed-"))
            subprocess.run(["cp", "-r", str(out / "logs"), str(kept)], check=False)
            sys.exit(f"octolog run failed ({proc.returncode}): its logs are kept in {kept}/logs")
        report(out, rows, wall, loops * n_loop)
        print(summary_text)
        if args.keep:
            subprocess.run(["cp", "-r", str(out), args.keep], check=True)


def _slope(t: np.ndarray, mb: np.ndarray, *, after_s: float | None = None) -> float:
    """MB per minute: over the whole run, a least-squares line; from `after_s` on (the steady state:
    after the first minute, whose keyframes build the map), the median of the pairwise slopes
    (Theil-Sen), which the end's one-off peak (the mapper's final map and files: +300-400 MB for a
    few seconds) does not tilt as it tilts a least-squares line."""
    if after_s is None:
        return float(np.polyfit(t / 60.0, mb, 1)[0]) if len(t) >= 3 and t[-1] > t[0] else float("nan")
    keep = t >= after_s
    t, mb = t[keep], mb[keep]
    return float(theilslopes(mb, t / 60.0)[0]) if len(t) >= 3 and t[-1] > t[0] else float("nan")


def report(out: Path, rows: list[dict], wall: float, n: int) -> None:
    per_min_ns = 60 * 10**9
    track: dict[int, list[float]] = {}
    mapper: dict[int, list[float]] = {}
    t_first = None
    for m in read_wire(out / "session.mcap", [topics.TRACKING_STATUS.name, topics.MAP_UPDATE.name]):
        msg = codec.decode(m.data, topics.BY_NAME[m.topic].msgtype)
        stamp = codec.stamp_ns(msg.header)
        t_first = stamp if t_first is None else t_first
        minute = (stamp - t_first) // per_min_ns
        (track if m.topic == topics.TRACKING_STATUS.name else mapper).setdefault(minute, []).append(msg.processing_ms)
    summary = json.loads((out / "summary.json").read_text())
    minutes = n / FPS / 60  # summary.json's duration is the looped source's: one loop
    total_mb = sum(p.stat().st_size for p in [out / "session.mcap", *(out / "rerun").glob("*.rrd")]) / 1e6
    print(f"\noctolog long-session pipeline benchmark: synthetic room, {n} frames ({minutes:.1f} min at {FPS} fps), "
          f"octolog run with its default outputs; wall {wall:.0f} s (real-time factor {minutes * 60 / wall:.2f}); "
          f"load average {os.getloadavg()[0]:.1f}\n")
    print("| minute | tracker ms/frame median / p90 | mapper ms/keyframe median / p90 (keyframes) |")
    print("|---|---|---|")
    for k in sorted(track):
        mp = mapper.get(k, [])
        print(f"| {k + 1} | {pct(track[k], 50):.1f} / {pct(track[k], 90):.1f} | "
              f"{pct(mp, 50):.0f} / {pct(mp, 90):.0f} ({len(mp)}) |")
    full = [k for k in sorted(track) if len(track[k]) >= 0.9 * 60 * FPS] or sorted(track)
    first, last = full[0], full[-1]
    print("\n| | value |\n|---|---|")
    print(f"| tracker last / first minute, median; p90 | {pct(track[last], 50) / pct(track[first], 50):.2f}x; "
          f"{pct(track[last], 90) / pct(track[first], 90):.2f}x |")
    mf, ml = mapper.get(first, []), mapper.get(last, [])
    if mf and ml:
        print(f"| mapper last / first minute, median | {pct(ml, 50) / pct(mf, 50):.2f}x |")
    print(f"| output size: total MB, MB per minute of camera | {total_mb:.0f}, {total_mb / minutes:.0f} |")
    stages = sorted({s for r in rows for s in r["mem"]})
    for s in stages:
        series = [(r["t"], r["mem"][s]) for r in rows if s in r["mem"] and r["mem"][s] > 0]
        if len(series) < 3:
            continue
        t, mb = np.array(series).T
        print(f"| {s}: peak RSS MB; growth MB per minute of wall time: whole run, after the first minute | "
              f"{mb.max():.0f}; {_slope(t, mb):+.1f}, {_slope(t, mb, after_s=60.0):+.1f} |")
    print(f"| keyframes | {summary['map']['keyframes']} |")
    ate = summary.get("ate") or {}
    print(f"| ATE RMSE, cm | {ate.get('rmse_m', float('nan')) * 100:.2f} |")


if __name__ == "__main__":
    if "--render-to" in sys.argv:
        i = sys.argv.index("--render-to")
        render_loop_mcap(Path(sys.argv[i + 1]), round(LOOP_S * FPS), int(sys.argv[sys.argv.index("--loops") + 1]))
    else:
        main()
