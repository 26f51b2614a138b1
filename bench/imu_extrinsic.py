"""A wrong camera-IMU rotation: what the IMU does to the tracker when its calibration is off.

The native tracker in-process, every frame (no transport, no pacing), on the synthetic fast turns
with its simulated D455 IMU, told a camera-IMU rotation off by each angle (about the axis
(0.6, 0.8, 0), or the x axis for 90 degrees: axes swapped), against the tracker without the IMU.
Per run: frames LOST, ATE, whether vision trusts the gyro at the end, and how many keyframes keep
a gyro factor in the back end.

    python bench/imu_extrinsic.py [--angles 0,3,10,30,90] [--source synthetic:300:motion=turns:exposure=10:imu=200]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from octolog.kit import metrics
from octolog.replay.imu import source_imu
from octolog.replay.sources import open_source
from octolog.tracker.interface import TrackingState
from octolog.tracker.slam import RgbdSlam
from octolog.tracker.pose import so3_exp


def run(source: str, off_deg: float | None) -> dict:
    """One tracker run: `off_deg` None tracks without the IMU."""
    src = open_source(source)
    imu = source_imu(src)
    slam = RgbdSlam()
    if off_deg is not None:
        axis = np.array([1.0, 0.0, 0.0]) if off_deg == 90 else np.array([0.6, 0.8, 0.0])
        wrong = np.eye(4)
        wrong[:3, :3] = so3_exp(np.radians(off_deg) * axis)
        slam.set_camera_from_imu(wrong)
    prev, lost = None, 0
    for frame in src.frames():
        if off_deg is not None:
            slam.add_imu(imu.samples.between(frame.stamp_ns - 50_000_000 if prev is None else prev, frame.stamp_ns))
        prev = frame.stamp_ns
        lost += slam.track(frame).state == TrackingState.LOST
    slam.finish()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trajectory.txt"
        metrics.write_tum(path, *slam.trajectory())
        ate = metrics.ate(metrics.read_tum(path), metrics.parse_tum(src.groundtruth_tum(), "gt"))
    gyro = slam.imu.inertial.gyro_trusted if off_deg is not None else None
    factors = sum(kf.gyro is not None for kf in slam.map.keyframes)
    return {"lost": lost, "ate_cm": ate.rmse * 100, "gyro": gyro, "factors": f"{factors}/{len(slam.map.keyframes)}"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--angles", default="0,3,10,30,90", help="degrees the camera-IMU rotation is off")
    ap.add_argument("--source", default="synthetic:300:motion=turns:exposure=10:imu=200")
    args = ap.parse_args()
    print(f"{args.source}, every frame, in-process")
    print(f"{'camera-IMU rotation':<22} {'LOST':>5} {'ATE cm':>7} {'gyro trusted':>13} {'keyframes with a factor':>24}")
    rows = [("without the IMU", None)] + [(f"{float(a):g} deg off", float(a)) for a in args.angles.split(",")]
    for name, off in rows:
        r = run(args.source, off)
        print(f"{name:<22} {r['lost']:>5} {r['ate_cm']:>7.2f} {str(r['gyro'] if off is not None else '-'):>13} "
              f"{r['factors']:>24}")


if __name__ == "__main__":
    main()
