"""Long-session tracker benchmark: the synthetic room looped for minutes at 30 fps, native tracker.

Does the tracker's cost grow with the session? One loop around the pillar (18 s, 540 frames, on the
periodic variant of the synthetic path so the loop joins smoothly) is rendered once into PNGs in a
temporary folder, then played again and again for `--minutes` (default 10: 18,000 frames) through
the tracker core in this process (back-end worker on, Rerun off, as `octolog track` runs it).
Decoding the PNGs happens outside the timed call. Printed per minute of sensor time: track-call
median and p90, keyframes, and the memory of the tracking process and its back-end worker; then the
first-versus-last-minute ratios, MB per 1,000 keyframes, the end-of-stream time (final BA) and ATE.

    python bench/long_session.py [--minutes 10] [--vocabulary FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from octolog.kit import metrics
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.replay.synthetic_trajectory import LOOP_S, camera_trajectory
from octolog.tracker.config import TrackerConfig
from octolog.tracker.factory import make_odometry

FPS = 30

from pipeline import pct  # noqa: E402  (bench/ is this script's folder)


def _mb(pid: int | str, key: str) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def loop_poses(n: int) -> np.ndarray:
    pos, rot = camera_trajectory(np.arange(n) / FPS, periodic=True)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = rot, pos
    return T


def render_loop(folder: Path, n_loop: int) -> None:
    """PNGs of one loop and meta.json; run in a child process, so the renderer's memory (open3d's
    ray caster, the textures) is not counted as the tracker's."""
    from octolog.replay.synthetic import SyntheticScene

    scene = SyntheticScene(n_frames=n_loop)
    for k, T in enumerate(loop_poses(n_loop)):
        rgb, depth = scene.render_pose(T)
        cv2.imwrite(str(folder / f"{k:04d}_rgb.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(folder / f"{k:04d}_depth.png"), depth)
    (folder / "meta.json").write_text(json.dumps({
        "intrinsics": dataclasses.asdict(scene.intrinsics), "depth_scale_m": scene.depth_scale_m,
        "start_ns": scene.config.start_ns}))


@dataclasses.dataclass
class Played:
    """What playing the loop left to report: the per-minute rows, each frame's stamp, the memory of the
    empty tracker (tracker; worker), the end-of-stream time and the tracking process's CPU seconds."""

    odom: Any  # the tracker make_odometry built (RgbdSlam's counts and worker are read too)
    rows: list[tuple]
    stamps: list[int]
    empty: tuple[float, float]
    end_s: float
    cpu_s: float


def _rendered_loop(tmp: str, n_loop: int, n: int, minutes: float) -> tuple[dict, Intrinsics]:
    """Render one loop into `tmp` in a child process; its meta.json and intrinsics."""
    t0 = time.monotonic()
    subprocess.run([sys.executable, __file__, "--render-to", tmp], check=True)
    meta = json.loads((Path(tmp) / "meta.json").read_text())
    K = Intrinsics(**{**meta["intrinsics"], "distortion": tuple(meta["intrinsics"]["distortion"])})
    print(f"rendered one loop ({n_loop} frames) in {time.monotonic() - t0:.0f} s; playing {n} frames "
          f"({minutes:g} min at {FPS} fps)", flush=True)
    return meta, K


def _play(cfg: TrackerConfig, tmp: str, meta: dict, K: Intrinsics, n: int, n_loop: int) -> Played:
    """The loop's PNGs played `n` frames through the tracker, a row printed per minute of sensor time."""
    per_min = 60 * FPS
    odom = make_odometry(cfg)
    worker = getattr(getattr(odom, "worker", None), "_proc", None)
    if getattr(odom, "worker", None) is not None:
        odom.worker.ready()  # its imports done: the empty tracker's memory below holds no keyframe
    empty = (_mb("self", "VmRSS"), _mb(worker.pid, "VmRSS") if worker else 0.0)
    stamps, ms, rows = [], [], []
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    for i in range(n):
        k = i % n_loop
        rgb = cv2.cvtColor(cv2.imread(f"{tmp}/{k:04d}_rgb.png", cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(f"{tmp}/{k:04d}_depth.png", cv2.IMREAD_ANYDEPTH)
        frame = RgbdFrame(seq=i, stamp_ns=meta["start_ns"] + round(i * 1e9 / FPS), rgb=rgb, depth=depth,
                          depth_scale_m=meta["depth_scale_m"], intrinsics=K)
        t = time.perf_counter()
        r = odom.track(frame)
        ms.append((time.perf_counter() - t) * 1e3)
        stamps.append(r.stamp_ns)
        if (i + 1) % per_min == 0 or i + 1 == n:
            lo = len(rows) * per_min
            rows.append((len(rows) + 1, pct(ms[lo:], 50), pct(ms[lo:], 90), odom.n_keyframes, odom.n_map_points,
                         _mb("self", "VmRSS"), _mb(worker.pid, "VmRSS") if worker else 0.0))
            print("minute {} | {:.1f} / {:.1f} ms | {} keyframes | {} points | {:.0f} MB + worker {:.0f} MB"
                  .format(*rows[-1]), flush=True)
    t_end = time.perf_counter()
    odom.finish()
    end_s = time.perf_counter() - t_end
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu_s = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    return Played(odom=odom, rows=rows, stamps=stamps, empty=empty, end_s=end_s, cpu_s=cpu_s)


def _ate_cm(played: Played, poses: np.ndarray, n: int, n_loop: int) -> float:
    """ATE RMSE of the final trajectory against the looped ground truth, in cm."""
    fs, fp = played.odom.trajectory()
    all_poses = np.stack([poses[i % n_loop] for i in range(n)])
    gt = metrics.Trajectory.from_matrices(np.array(played.stamps), all_poses)
    return metrics.ate(metrics.Trajectory.from_matrices(np.array(fs), np.array(fp)), gt).rmse * 100.0


def _report(played: Played, ate: float, n: int, minutes: float) -> None:
    """The per-minute table and the summary table, as Markdown."""
    odom, rows, empty = played.odom, played.rows, played.empty
    first, last = rows[0], rows[-1]
    kf_growth = last[3] - first[3]
    mb_per_1000 = (last[5] - first[5]) / kf_growth * 1000.0 if kf_growth > 0 else float("nan")
    wmb_per_1000 = (last[6] - first[6]) / kf_growth * 1000.0 if kf_growth > 0 else float("nan")
    # per keyframe from the empty tracker to the first minute: what a map of that size holds (with the
    # frames' trajectory, small); the growth after it, when the map still grows on later minutes
    kf1 = max(1, first[3])
    mb_first = ((first[5] - empty[0]) / kf1 * 1000.0, (first[6] - empty[1]) / kf1 * 1000.0)
    load = os.getloadavg()
    print()
    print(f"octolog long-session tracker benchmark: synthetic room, {n} frames ({minutes:g} min at {FPS} fps), "
          f"one {LOOP_S:g} s loop repeated; native tracker, worker on, Rerun off; load average {load[0]:.1f}")
    print()
    print("| minute | track ms median / p90 | keyframes | map points | tracker RSS MB | worker RSS MB |")
    print("|---|---|---|---|---|---|")
    for m, p50, p90, kf, pts, rss, wrss in rows:
        print(f"| {m} | {p50:.1f} / {p90:.1f} | {kf} | {pts} | {rss:.0f} | {wrss:.0f} |")
    print()
    print("| | value |")
    print("|---|---|")
    print(f"| last minute / first minute, median | {last[1] / first[1]:.2f}x |")
    print(f"| last minute / first minute, p90 | {last[2] / first[2]:.2f}x |")
    print(f"| peak RSS, MB (tracker process VmHWM + worker VmHWM) | {_mb('self', 'VmHWM'):.0f} + "
          f"{odom.worker_peak_rss_mb:.0f} |")
    print(f"| RSS of the empty tracker (imports, worker ready), MB (tracker; worker) | {empty[0]:.0f}; "
          f"{empty[1]:.0f} |")
    print(f"| MB per 1,000 keyframes, empty tracker to the first minute (tracker; worker) | {mb_first[0]:.0f}; "
          f"{mb_first[1]:.0f} |")
    print(f"| MB per 1,000 keyframes after the first minute (tracker; worker) | {mb_per_1000:.0f}; "
          f"{wmb_per_1000:.0f} |")
    if kf_growth == 0:
        print("| (after the first minute: no keyframe was added, so no growth per keyframe to measure) | |")
    print(f"| keyframes | {odom.n_keyframes} |")
    print(f"| end of stream (finish: last back end + final BA), s | {played.end_s:.1f} |")
    print(f"| CPU of the tracking process, ms per frame (worker not counted while alive) | "
          f"{played.cpu_s / n * 1e3:.1f} |")
    print(f"| ATE RMSE, cm (final trajectory) | {ate:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="session length in sensor time (default 10)")
    ap.add_argument("--vocabulary", default="", help="ORB vocabulary for place recognition (default: none)")
    ap.add_argument("--render-to", help=argparse.SUPPRESS)
    args = ap.parse_args()
    n_loop = round(LOOP_S * FPS)
    if args.render_to:
        render_loop(Path(args.render_to), n_loop)
        return
    n = round(args.minutes * 60 * FPS)
    poses = loop_poses(n_loop)
    cfg = TrackerConfig(vocabulary=args.vocabulary)
    with tempfile.TemporaryDirectory(prefix="octolog-long-") as tmp:
        meta, K = _rendered_loop(tmp, n_loop, n, args.minutes)
        played = _play(cfg, tmp, meta, K, n, n_loop)
    _report(played, _ate_cm(played, poses, n, n_loop), n, args.minutes)


if __name__ == "__main__":
    main()
