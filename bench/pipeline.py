"""End-to-end pipeline benchmark on TUM fr1/xyz first 300 (or any source).

Runs `octolog run` (replay, tracker, mapper, session logger as separate processes over Zenoh,
Rerun off), then reads the session MCAP for per-stage figures, and runs the same tracker and mapper
cores in one process with no transport as the reference. Prints one table.

    python bench/pipeline.py [--source tum:PATH] [--repeat 3]

Per-stage latency:
- tracker: its own processing time per frame (TrackingStatus.processing_ms);
- frame→pose: wall time from the logger receiving a frame to it receiving that frame's status
  (transport + queueing + tracking);
- mapper: processing time per keyframe (MapUpdate.processing_ms).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def default_source() -> str:
    data = Path(os.environ.get("OCTOLOG_DATA", ROOT.parent / "shared" / "data"))
    folder = data / "tum" / "rgbd_dataset_freiburg1_xyz_first300"
    if not folder.is_dir():
        sys.exit(f"bench: {folder} not found; pass --source or set OCTOLOG_DATA")
    return f"tum:{folder}"


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def run_pipeline(source: str, out: Path) -> dict:
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "octolog", "run", "--source", source, "--out", str(out), "--quiet",
                    "--rerun", "off"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    wall = time.monotonic() - t0
    from octolog.kit.mcaplog import read_messages
    from octolog.schemas import codec, topics

    frame_rx: dict[int, int] = {}
    track_ms, latency_ms, map_ms = [], [], []
    seqs = []
    for m in read_messages(out / "session.mcap"):
        if m.topic == topics.RGBD.name:
            seq = int.from_bytes(m.data[4:12], "little")  # CDR: 4-byte encapsulation, then uint64 seq
            frame_rx[seq] = m.log_time_ns
            seqs.append(seq)
        elif m.topic == topics.TRACKING_STATUS.name:
            st = codec.decode(m.data, topics.TRACKING_STATUS.msgtype)
            track_ms.append(st.processing_ms)
            if st.seq in frame_rx:
                latency_ms.append((m.log_time_ns - frame_rx[st.seq]) / 1e6)
        elif m.topic == topics.MAP_UPDATE.name:
            map_ms.append(codec.decode(m.data, topics.MAP_UPDATE.msgtype).processing_ms)
    import json

    summary = json.loads((out / "summary.json").read_text())
    return {"wall": wall, "frames": summary["tracked_frames"], "duration": summary["duration_s"],
            "ate_cm": (summary["ate"] or {}).get("rmse_m", float("nan")) * 100, "track_ms": track_ms,
            "latency_ms": latency_ms, "map_ms": map_ms, "keyframes": len(map_ms)}


def run_in_process(source: str) -> dict:
    """The reference: the same cores, one process, no transport, no logging."""
    from octolog.mapper.config import MapperConfig
    from octolog.mapper.core import make_mapper
    from octolog.replay.sources import open_source
    from octolog.tracker.config import TrackerConfig, for_source
    from octolog.tracker.factory import make_odometry

    src = open_source(source)
    frames = list(src.frames())  # decode up front: the pipeline's replay decodes concurrently
    odom, mapper = make_odometry(for_source(TrackerConfig(), src)), make_mapper(MapperConfig())
    track_ms, map_ms = [], []
    t0 = time.monotonic()
    for f in frames:
        t = time.perf_counter()
        res = odom.track(f)
        track_ms.append((time.perf_counter() - t) * 1e3)
        if res.is_keyframe:
            t = time.perf_counter()
            mapper.integrate(res.keyframe_id, res.world_from_camera, f)
            map_ms.append((time.perf_counter() - t) * 1e3)
    wall = time.monotonic() - t0
    return {"wall": wall, "frames": len(frames), "duration": src.duration_ns * 1e-9, "track_ms": track_ms,
            "map_ms": map_ms, "keyframes": len(map_ms)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=None)
    ap.add_argument("--repeat", type=int, default=3, help="pipeline runs (medians over runs)")
    args = ap.parse_args()
    source = args.source or default_source()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            runs.append(run_pipeline(source, Path(tmp) / f"run{i}"))
    ref = run_in_process(source)

    def med(key: str) -> float:
        return statistics.median(r[key] for r in runs)

    fps = [r["frames"] / r["wall"] for r in runs]
    rtf = [r["duration"] / r["wall"] for r in runs]
    track = [x for r in runs for x in r["track_ms"]]
    lat = [x for r in runs for x in r["latency_ms"]]
    mp = [x for r in runs for x in r["map_ms"]]
    ref_fps = ref["frames"] / ref["wall"]
    rows = [
        ("frames", f"{runs[0]['frames']}", f"{ref['frames']}", ""),
        ("wall time, s (median of runs)", f"{med('wall'):.1f}", f"{ref['wall']:.1f}", f"{med('wall') / ref['wall']:.2f}x"),
        ("end-to-end frames/s", f"{statistics.median(fps):.1f}", f"{ref_fps:.1f}",
         f"{statistics.median(fps) / ref_fps:.2f}x"),
        ("real-time factor (sequence s / wall s)", f"{statistics.median(rtf):.2f}",
         f"{ref['duration'] / ref['wall']:.2f}", ""),
        ("tracker ms/frame median / p90", f"{pct(track, 50):.1f} / {pct(track, 90):.1f}",
         f"{pct(ref['track_ms'], 50):.1f} / {pct(ref['track_ms'], 90):.1f}", ""),
        ("frame->pose latency ms median / p90", f"{pct(lat, 50):.1f} / {pct(lat, 90):.1f}", "-", ""),
        ("mapper ms/keyframe median / p90", f"{pct(mp, 50):.1f} / {pct(mp, 90):.1f}",
         f"{pct(ref['map_ms'], 50):.1f} / {pct(ref['map_ms'], 90):.1f}", ""),
        ("keyframes", f"{runs[0]['keyframes']}", f"{ref['keyframes']}", ""),
        ("ATE RMSE, cm", f"{runs[0]['ate_cm']:.2f}", "-", ""),
    ]
    print(f"octolog pipeline benchmark: {source}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"pipeline = 4 processes over Zenoh (peer, loopback), Rerun off, {args.repeat} runs; "
          f"reference = same cores in one process, frames pre-decoded, no transport")
    w = max(len(r[0]) for r in rows)
    print(f"{'':<{w}}  {'pipeline':>14}  {'in-process':>14}  {'ratio':>7}")
    for name, a, b, ratio in rows:
        print(f"{name:<{w}}  {a:>14}  {b:>14}  {ratio:>7}")


if __name__ == "__main__":
    main()
