"""What a saved SLAM map costs: its size on disk, the seconds to load and to save it, the memory it takes.

    python bench/mapfile.py SESSION_OR_MAP [--repeat 3]

Loads the map (tracker/mapfile.py: load_map), adopts it in a fresh tracker (with the place index made
again from the keyframes' descriptors, when `--vocabulary` is given) and saves it again; medians over
`--repeat` runs, and the process's resident memory before and after one load.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

from octolog.tracker.config import TrackerConfig
from octolog.tracker.factory import make_odometry
from octolog.tracker.mapfile import load_map, map_path


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map", help="a session folder or its slam_map.npz")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--vocabulary", default="", help="the tracker's vocabulary (the place index is made with it)")
    args = ap.parse_args()
    path = map_path(args.map)
    before = rss_mb()
    saved = load_map(path)
    after = rss_mb()
    load_s, adopt_s, save_s = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            saved = load_map(path)
            t1 = time.perf_counter()
            slam = make_odometry(TrackerConfig(vocabulary=args.vocabulary, background=False))
            t2 = time.perf_counter()
            slam.adopt_map(saved)
            t3 = time.perf_counter()
            slam.save_map(Path(tmp) / "again.npz")
            t4 = time.perf_counter()
            load_s.append(t1 - t0)
            adopt_s.append(t3 - t2)
            save_s.append(t4 - t3)
        same = (Path(tmp) / "again.npz").read_bytes() == path.read_bytes()
    h = saved.header
    print(f"{path}: {h['keyframes']} keyframes, {h['map_points']} map points, {path.stat().st_size / 1e6:.1f} MB on disk")
    print("| load, s | adopt (place index), s | save, s | resident memory of one loaded map, MB | saved again: same bytes |")
    print("|---|---|---|---|---|")
    print(f"| {statistics.median(load_s):.2f} | {statistics.median(adopt_s):.2f} | {statistics.median(save_s):.2f} | "
          f"{after - before:.0f} | {same} |")
    print(f"peak resident memory of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
