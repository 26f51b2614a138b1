"""Occupancy map benchmark: pyoctomap insertPointCloud versus our NumPy VoxelOccupancyMap.

On TUM fr1/xyz first 300 (OCTOLOG_DATA or ../shared/data) with ground-truth poses, every
`--every`-th frame as a keyframe; falls back to the synthetic scene when the data is absent.
For the raw back-projected cloud (stride 1) and the keyframe cloud the mapper uses (stride 2,
1 cm voxel grid, SOR): per-keyframe insert time (median, p90, total), occupied/free voxels,
state agreement with pyoctomap (discretize=True) over voxels either map knows, peak memory.

    python bench/mapper.py [--frames 300] [--every 10] [--max-range 4.0]
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from octolog.mapper.cloud import backproject, keyframe_cloud, transform  # noqa: E402
from octolog.mapper.octree import OccupancyOctree  # noqa: E402
from octolog.mapper.voxelmap import VoxelOccupancyMap  # noqa: E402


def keyframes(frames: int, every: int):
    data = Path(os.environ.get("OCTOLOG_DATA", ROOT.parent / "shared" / "data"))
    folder = data / "tum" / "rgbd_dataset_freiburg1_xyz_first300"
    if folder.is_dir():
        from octolog.kit.metrics import associate, read_tum
        from octolog.kit.tum import open_tum

        seq = open_tum(folder)
        gt = read_tum(seq.groundtruth)
        fr = [f for i, f in enumerate(seq.frames(0, frames)) if i % every == 0]
        ia, ib = associate(np.array([f.stamp_ns for f in fr]), gt.stamps_ns, 20_000_000)
        mats = gt.matrices()
        return f"TUM fr1/xyz first {frames}, every {every}th frame", [(fr[i], mats[j]) for i, j in zip(ia, ib)]
    from octolog.replay.synthetic import SyntheticScene

    sc = SyntheticScene(n_frames=frames)
    fr = [f for i, f in enumerate(sc.frames()) if i % every == 0]
    return f"synthetic scene, {frames} frames, every {every}th", [(f, sc.pose(f.seq)) for f in fr]


def run(method: str, clouds, max_range: float, trace: bool = False):
    """Insert all clouds; returns (ms per keyframe, map, peak traced MiB if `trace`)."""
    if method.startswith("octomap"):
        m = OccupancyOctree(0.05)
        discretize = method.endswith("discretize")
    else:
        m = VoxelOccupancyMap(0.05)
    ms = []
    if trace:
        tracemalloc.start()
    for pts, cols, T in clouds:
        t0 = time.perf_counter()
        if method == "octomap":
            m.tree.insertPointCloud(pts, T[:3, 3].copy(), max_range=max_range, lazy_eval=False,
                                    discretize=False)
        elif method == "octomap discretize":
            m.tree.insertPointCloud(pts, T[:3, 3].copy(), max_range=max_range, lazy_eval=False,
                                    discretize=discretize)
        elif method == "numpy":
            m.insert(pts, T[:3, 3], max_range_m=max_range)
        else:  # numpy with colour
            m.insert(pts, T[:3, 3], colours=cols, max_range_m=max_range)
        ms.append((time.perf_counter() - t0) * 1e3)
    peak = float("nan")
    if trace:
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    if hasattr(m, "_leaf_cache"):
        m._leaf_cache = None  # the tree was filled directly, bypassing the wrapper
    return ms, m, peak


def states(m) -> dict[tuple[int, int, int], int]:
    out = {}
    for c, s in ((m.free_centres(), 0), (m.occupied_centres(), 1)):
        for k in map(tuple, np.floor(c / 0.05).astype(np.int64).tolist()):
            out[k] = s
    return out


def agreement(a: dict, b: dict) -> float:
    union = a.keys() | b.keys()
    return sum(1 for k in union if a.get(k, -1) == b.get(k, -1)) / max(1, len(union))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--max-range", type=float, default=4.0)
    args = ap.parse_args()
    name, kfs = keyframes(args.frames, args.every)
    raw, filt = [], []
    for f, T in kfs:
        p, c = backproject(f.depth, f.rgb, f.intrinsics, f.depth_scale_m, max_range_m=args.max_range, stride=1)
        raw.append((np.ascontiguousarray(transform(p, T)), c, T))
        p, c = keyframe_cloud(f.depth, f.rgb, f.intrinsics, f.depth_scale_m, T, max_range_m=args.max_range)
        filt.append((np.ascontiguousarray(p), c, T))
    print(f"{name}: {len(kfs)} keyframes, 5 cm, max range {args.max_range} m, "
          f"raw ~{np.median([len(r[0]) for r in raw]):.0f} pts, filtered ~{np.median([len(r[0]) for r in filt]):.0f} pts")
    head = f"{'cloud':9} {'method':19} {'median ms':>9} {'p90 ms':>8} {'total s':>8} {'occupied':>9} {'free':>8} {'agree %':>8} {'peak MiB':>8} {'map MiB':>8}"
    print(head)
    print("-" * len(head))
    for label, clouds in (("raw", raw), ("filtered", filt)):
        ref_states = ref_bt = None
        medians = {}
        for method in ("octomap", "octomap discretize", "numpy", "numpy +colour"):
            ms, m, _ = run(method, clouds, args.max_range)
            peak = run(method, clouds[:5], args.max_range, trace=True)[2]  # tracing slows Python: separate pass
            st = states(m)
            if method == "octomap discretize":
                ref_states, ref_bt = st, m.bt_bytes()
            same_bt = "" if ref_bt is None or method == "octomap discretize" else \
                f"  .bt {'equal' if m.bt_bytes() == ref_bt else 'DIFFERS'}"
            agree = agreement(ref_states, st) * 100 if ref_states is not None else float("nan")
            s = m.stats()
            medians[method] = float(np.median(ms))
            print(f"{label:9} {method:19} {np.median(ms):9.1f} {np.percentile(ms, 90):8.1f} {sum(ms) / 1e3:8.2f} "
                  f"{s['occupied_voxels']:9d} {s['free_voxels']:8d} {agree:8.3f} {peak:8.1f} {s['memory_bytes'] / 2**20:8.1f}{same_bt}")
        for method in ("octomap", "octomap discretize"):
            print(f"{'':9} median speed-up numpy vs {method}: {medians[method] / medians['numpy']:.2f}x "
                  f"(with colour {medians[method] / medians['numpy +colour']:.2f}x)")
    print("agree %: occupied/free/unknown state equal to pyoctomap discretize=True, over voxels either map knows;")
    print("peak MiB: tracemalloc over the first 5 inserts, in a separate untimed pass (Python/NumPy allocations only; OctoMap's C++ heap is not traced);")
    print("map MiB: the map's own size (OctoMap memoryUsage(), or our arrays' nbytes).")


if __name__ == "__main__":
    main()
