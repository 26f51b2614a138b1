"""Tracker benchmark: the native tracker and the ORB-SLAM3 backend side by side on one sequence.

Each backend runs the tracker core directly (no transport, Rerun off) in its own subprocess, so
peak memory (VmHWM) is per backend. Frames are decoded one at a time outside the timed call; the
per-frame time is the wall time of `track()` (ORB-SLAM3 also works on its local-mapping and
loop-closing threads: CPU time counts every thread). ORB-SLAM3 is not deterministic, so it runs
`--orb-runs` times (default 3) and the table quotes the median ATE and every run's.

    python bench/tracker.py [--cases first300,first300x3,turns] [--vocabulary FILE] [--orb-runs 3]

The cases are bench/devdata.py's: TUM fr1/xyz first300 as recorded, the same every 3rd frame
re-timed to 30 fps (3x the motion at the camera's rate), and the synthetic room with 150-210 deg/s
head turns, 8 ms motion blur and Kinect depth noise; one table each. Besides ATE, each table
counts the published poses whose step from the previous published pose is more than 5 cm off
the ground truth's step (a confident wrong pose: what a mapper would integrate).

Without --vocabulary one is built with `octolog vocab build` from TUM fr1/xyz first300's rgb/
folder (k 10, L 6, seed 0) and cached in --cache (default /tmp/octolog-bench/vocab).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from octolog.kit import metrics
from octolog.tracker.config import TrackerConfig, for_source
from octolog.tracker.factory import make_odometry
from octolog.tracker.interface import TrackingState
from octolog.tracker.slam import RgbdSlam
from octolog.tracker.orbslam3 import OrbSlam3Odometry

ROOT = Path(__file__).resolve().parents[1]


from devdata import CASES, case_source, first300, open_case, step_errors  # noqa: E402  (bench/ is this script's folder)
from pipeline import pct  # noqa: E402


def _vm(key: str) -> float:
    """VmHWM / VmRSS of this process in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


# ----------------------------------------------------------------------------------------------
# Worker: one backend, one run, in its own process.


def worker(backend: str, source: str, sets: list[str], vocabulary: str, result_path: Path) -> None:
    src = open_case(source, sets)
    frames = src.frames()
    first = next(frames)
    cfg = for_source(TrackerConfig(engine=backend, vocabulary=vocabulary), src)
    odom = make_odometry(cfg)
    rss_before = _vm("VmRSS")
    t0 = time.perf_counter()
    if isinstance(odom, OrbSlam3Odometry):
        odom.start(first)  # ORB-SLAM3: settings + vocabulary load, reported apart from frame times
    worker_startup_cpu = 0.0
    if getattr(odom, "worker", None) is not None:  # native: the back-end worker's imports, as ORB-SLAM3's start
        worker_startup_cpu = odom.worker.ready()
    startup_s = time.perf_counter() - t0
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    kids0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall0 = time.perf_counter()
    ms, stamps, poses, states, moved, found_again = [], [], [], [], [], []
    frame = first
    while frame is not None:
        t = time.perf_counter()
        r = odom.track(frame)
        ms.append((time.perf_counter() - t) * 1e3)
        stamps.append(r.stamp_ns)
        poses.append(r.world_from_camera)
        states.append(r.state)
        moved.append(r.map_moved_m)
        found_again.append(bool(r.relocalised))
        frame = next(frames, None)
    final_tum = None
    odom.finish()  # native: waits for the back end; ORB-SLAM3: nothing (close() below stops it)
    if isinstance(odom, RgbdSlam):  # the trajectory the back end corrected
        fs, fp = odom.trajectory()
        final_tum = metrics.format_tum(np.array(fs), np.array(fp))
    n_keyframes = odom.n_keyframes
    orb_keyframes = None
    if isinstance(odom, OrbSlam3Odometry):  # stop its threads, read its keyframes and trajectory
        odom.close()
        final_tum, orb_keyframes = odom.final_trajectory_tum, odom.orb_keyframes
    wall_s = time.perf_counter() - wall0
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    # the native back end's worker process counts too (finish() waited for it, so it is reaped)
    kids1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime) \
        + (kids1.ru_utime - kids0.ru_utime) + (kids1.ru_stime - kids0.ru_stime) - worker_startup_cpu
    result_path.write_text(json.dumps({
        "backend": backend, "ms": ms, "states": states, "map_moved_m": moved, "relocalised": found_again, "n_keyframes": n_keyframes, "orb_keyframes": orb_keyframes,
        "online_tum": metrics.format_tum(np.array(stamps), np.array(poses)), "final_tum": final_tum,
        "startup_s": startup_s, "wall_s": wall_s, "cpu_s": cpu_s, "rss_before_mb": rss_before,
        "peak_rss_mb": _vm("VmHWM"), "worker_peak_rss_mb": getattr(odom, "worker_peak_rss_mb", 0.0),
        "worker_file_rss_mb": getattr(odom, "worker_file_rss_mb", 0.0),
        "readout_ms": cfg.rolling_shutter_ms,
    }))


def run_worker(backend: str, source: str, sets: list[str], vocabulary: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        res = Path(tmp) / "result.json"
        # ORB-SLAM3 prints its progress on stdout: keep it out of the table
        proc = subprocess.run([sys.executable, __file__, "--worker", backend, "--source", source,
                               "--sets", json.dumps(sets), "--vocabulary", vocabulary, "--result", str(res)],
                              cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if proc.returncode != 0:
            sys.exit(f"bench: {backend} worker failed:\n{proc.stderr}")
        return json.loads(res.read_text())


# ----------------------------------------------------------------------------------------------
# Vocabulary


def ensure_vocabulary(given: str | None, cache: Path) -> tuple[str, str]:
    """(path, note): the given file, a cached build from first300's images, or a fresh `octolog vocab build`."""
    if given:
        return given, f"vocabulary: {given} (given)"
    rgb = first300() / "rgb"
    params = ["--k", "10", "--levels", "6", "--features", "1000", "--seed", "0"]
    key = hashlib.sha256(f"{rgb.resolve()} {' '.join(params)}".encode()).hexdigest()[:12]
    out = cache / f"{rgb.parent.name}_k10_L6_{key}.txt"
    cmd = f"octolog vocab build {rgb} {' '.join(params)} --out {out}"
    if out.is_file():
        return str(out), f"vocabulary: cached {out} (made by `{cmd}`)"
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "octolog", "vocab", "build", str(rgb), *params, "--out", str(out),
                    "--quiet"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return str(out), f"vocabulary: built now by `{cmd}` in {time.monotonic() - t0:.0f} s"


# ----------------------------------------------------------------------------------------------


def ate_cm(tum: str | None, gt) -> float:
    if not tum:
        return float("nan")
    return metrics.ate(metrics.parse_tum(tum), gt).rmse * 100.0


def cm(v: float) -> str:
    return "–" if v != v else f"{v:.2f}"  # NaN: this backend has no such trajectory


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="first300,first300x3,turns", help=f"of {', '.join(CASES)}")
    ap.add_argument("--source", help=argparse.SUPPRESS)
    ap.add_argument("--sets", default="[]", help=argparse.SUPPRESS)
    ap.add_argument("--vocabulary", default=None, metavar="FILE", help="ORB vocabulary (default: build and cache one)")
    ap.add_argument("--orb-runs", type=int, default=3, help="ORB-SLAM3 runs (default 3; it is not deterministic)")
    ap.add_argument("--cache", default="/tmp/octolog-bench/vocab", help="where a built vocabulary is kept")
    ap.add_argument("--worker", choices=("native", "orbslam3"), help=argparse.SUPPRESS)
    ap.add_argument("--result", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.source, json.loads(args.sets), args.vocabulary or "", Path(args.result))
        return

    vocabulary, voc_note = ensure_vocabulary(args.vocabulary, Path(args.cache))
    try:
        from importlib.metadata import version

        orb_version = version("pyorbslam3")
    except Exception:
        orb_version = "?"
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor() or "?")
    print("octolog tracker benchmark")
    print(f"machine: {cpu}, {os.cpu_count()} cores, {platform.machine()}, Python {platform.python_version()}")
    print(f"native: tracker.odometry in-process, Rerun off, 1 run (deterministic); ORB-SLAM3: pyorbslam3 {orb_version} "
          f"RGB-D, {args.orb_runs} runs (not deterministic), keyframes published by pose distance "
          "(the binding reports none), 'own' = ORB-SLAM3's keyframe count at shutdown")
    print(voc_note)
    for name in args.cases.split(","):
        print()
        bench_case(name, vocabulary, args.orb_runs)


def published(r: dict, gt: metrics.Trajectory) -> dict:
    """The tracked frames' per-frame poses (as published) against the truth: bad steps, ATE."""
    traj = metrics.parse_tum(r["online_tum"])
    ok = np.array([s == TrackingState.OK for s in r["states"]])
    stamps, poses = traj.stamps_ns[ok], traj.matrices()[ok]
    steps = step_errors(list(stamps), list(poses), gt, list(np.asarray(r["map_moved_m"])[ok]),
                        relocalised=list(np.asarray(r["relocalised"], dtype=bool)[ok]))
    tracked = metrics.Trajectory.from_matrices(stamps, poses)
    return {**steps, "ate_cm": metrics.ate(tracked, gt).rmse * 100 if len(stamps) > 2 else float("nan")}


def bench_case(name: str, vocabulary: str, orb_runs: int) -> None:
    source, sets = case_source(name)
    gt_text = open_case(source, sets).groundtruth_tum()
    if not gt_text:
        sys.exit(f"bench: {source} has no ground truth")
    gt = metrics.parse_tum(gt_text)
    load0 = os.getloadavg()
    native = run_worker("native", source, sets, vocabulary)
    orbs = [run_worker("orbslam3", source, sets, vocabulary) for _ in range(orb_runs)]
    load1 = os.getloadavg()
    pub_n, pub_o = published(native, gt), [published(r, gt) for r in orbs]

    def ok(r: dict) -> int:
        return sum(s == TrackingState.OK for s in r["states"])

    n = len(native["states"])
    orb_final = [ate_cm(r["final_tum"], gt) for r in orbs]
    orb_ms = [x for r in orbs for x in r["ms"]]
    finals = ", ".join(cm(a) for a in orb_final)

    def med(key: str) -> float:
        return statistics.median(r[key] for r in orbs)

    rows = [
        ("ATE RMSE, cm (per-frame poses as published, tracked frames)", cm(pub_n["ate_cm"]),
         f"{cm(statistics.median(p['ate_cm'] for p in pub_o))} (runs: {', '.join(cm(p['ate_cm']) for p in pub_o)})"),
        ("published steps > 5 cm off the truth's, unflagged / at an announced map correction or relocalisation",
         f"{pub_n['bad_steps']} / {pub_n['flagged_steps']}",
         f"{statistics.median(p['bad_steps'] for p in pub_o):.0f} / - (runs: {', '.join(str(p['bad_steps']) for p in pub_o)}; "
         "it announces none)"),
        ("worst unflagged step error, cm", f"{pub_n['worst_step_m'] * 100:.1f}",
         f"{statistics.median(p['worst_step_m'] for p in pub_o) * 100:.1f}"),
        ("ATE RMSE, cm (final trajectory after back end)", cm(ate_cm(native["final_tum"], gt)),
         f"{cm(statistics.median(orb_final))} (runs: {finals})"),
        ("frames tracked (state OK) / frames", f"{ok(native)} / {n}",
         " / ".join([", ".join(str(ok(r)) for r in orbs), str(len(orbs[0]['states']))])),
        ("ms per frame, median / p90 (track call)", f"{pct(native['ms'], 50):.1f} / {pct(native['ms'], 90):.1f}",
         f"{pct(orb_ms, 50):.1f} / {pct(orb_ms, 90):.1f}"),
        ("CPU time, all threads and processes: s for the sequence (ms per frame)",
         f"{native['cpu_s']:.1f} ({native['cpu_s'] / n * 1e3:.1f})",
         f"{med('cpu_s'):.1f} ({med('cpu_s') / len(orbs[0]['states']) * 1e3:.1f})"),
        ("keyframes", f"{native['n_keyframes']}",
         f"{statistics.median(r['orb_keyframes'] or 0 for r in orbs):.0f} own; "
         f"{statistics.median(r['n_keyframes'] for r in orbs):.0f} published"),
        ("startup, s (native: back-end worker ready; ORB-SLAM3: settings + vocabulary load; not in CPU time)",
         f"{native['startup_s']:.2f}", f"{med('startup_s'):.2f}"),
        ("peak RSS, MB (process VmHWM; native: + its back-end worker process)",
         f"{native['peak_rss_mb']:.0f} + {native['worker_peak_rss_mb']:.0f}",
         f"{max(r['peak_rss_mb'] for r in orbs):.0f}"),
        ("peak memory, MB, shared libraries counted once (native: the worker's file-backed pages are the "
         "numpy/OpenCV libraries the tracker maps too)",
         f"{native['peak_rss_mb']:.0f} + {native['worker_peak_rss_mb'] - native['worker_file_rss_mb']:.0f}",
         f"{max(r['peak_rss_mb'] for r in orbs):.0f}"),
        ("RSS before tracking, MB (imports; native: and its vocabulary, ORB-SLAM3 loads its own later)",
         f"{native['rss_before_mb']:.0f}",
         f"{med('rss_before_mb'):.0f}"),
    ]
    print(f"## {name}: {CASES[name].about}: {n} frames; load average {load0[0]:.1f} before, {load1[0]:.1f} after (shared machine); "
          f"native rolling-shutter readout {native['readout_ms']:g} ms")
    print()
    print("| | native | ORB-SLAM3 |")
    print("|---|---|---|")
    for name, a, b in rows:
        print(f"| {name} | {a} | {b} |")


if __name__ == "__main__":
    main()
