"""Rolling-shutter readout sweep: which readout time explains a camera's images best.

Runs the native tracker over one sequence once per candidate readout time and prints, per value,
the tracker's own fit quality (the RMS reprojection error of each frame's inliers, in pixels of
the keypoint's pyramid level; no ground truth) and, when the source has ground truth, the ATE of
the final trajectory. The residual's curve is shallow near its minimum, so the estimate is the
vertex of a parabola fitted to it over the sweep (median and mean residual both printed); the
ATE column only shows whether that choice also lands near the most accurate one.

    python bench/readout.py [--source tum:PATH] [--ms 0,5,10,15,20,25,30,35]

This is how `octolog.kit.tum.TUM_READOUT_S["freiburg1"]` was picked (docs/results.md).
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np

from octolog.kit import metrics
from octolog.replay.sources import open_source
from octolog.tracker.config import TrackerConfig
from octolog.tracker.factory import make_odometry
from octolog.tracker.interface import TrackingState

ROOT = Path(__file__).resolve().parents[1]

from pipeline import default_source  # noqa: E402  (bench/ is this script's folder)


def run(frames: list, readout_ms: float, groundtruth: str | None) -> tuple[float, float, int, float | None]:
    odom = make_odometry(TrackerConfig(rolling_shutter_ms=readout_ms))
    results = [odom.track(f) for f in frames]
    odom.finish()
    residuals = [r.residual for r in results if r.state == TrackingState.OK and np.isfinite(r.residual)]
    ate = None
    if groundtruth:
        stamps, poses = odom.trajectory()
        est = metrics.Trajectory.from_matrices(np.array(stamps), np.array(poses))
        ate = metrics.ate(est, metrics.parse_tum(groundtruth)).rmse
    return statistics.median(residuals), statistics.fmean(residuals), len(residuals), ate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=None, help="frame source (default: TUM fr1/xyz first300 under $OCTOLOG_DATA)")
    ap.add_argument("--ms", default="0,5,10,15,20,25,30,35", help="readout times to try, ms")
    args = ap.parse_args()

    source = args.source or default_source()
    src = open_source(source)
    frames = list(src.frames())  # decoded once: every run sees the same frames
    gt = src.groundtruth_tum()
    values = [float(v) for v in args.ms.split(",")]
    rows = [(ms, *run(frames, ms, gt)) for ms in values]
    best = min(rows, key=lambda r: r[1])
    x = np.array([r[0] for r in rows])
    vertex = {}
    for name, col in (("median", 1), ("mean", 2)):
        c2, c1, _ = np.polyfit(x, np.array([r[col] for r in rows]), 2)
        vertex[name] = -c1 / (2.0 * c2) if c2 > 0 else float("nan")
    print(f"octolog readout sweep: {source} ({len(frames)} frames); source's own value: {1e3 * src.readout_s:g} ms")
    print()
    print("| readout ms | residual median | residual mean | frames OK | ATE cm (final) |")
    print("|---|---|---|---|---|")
    for ms, med, mean, n, ate in rows:
        mark = " **" if ms == best[0] else ""
        ate_s = "–" if ate is None else f"{ate * 100:.2f}"
        print(f"| {ms:g}{mark} | {med:.4f} | {mean:.4f} | {n} | {ate_s} |")
    print()
    print(f"lowest median residual: {best[0]:g} ms; parabola vertex: {vertex['median']:.1f} ms (median), "
          f"{vertex['mean']:.1f} ms (mean)")


if __name__ == "__main__":
    main()
