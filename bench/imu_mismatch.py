"""The IMU nobody calibrated: tracking with an IMU whose noise, mounting and clock differ from what the
tracker is told, against vision alone, through `octolog run` (every frame, unpaced: the figures are
the tracker's, not the machine's).

The synthetic room's simulated IMU at 200 Hz (turn-on biases of a consumer MEMS part), with one
mismatch at a time against the D455 datasheet figures and the identity mounting the tracker assumes:
its white noise and bias random walk scaled (`imunoise=X`), its axes turned by DEG about a fixed
oblique axis (`imurot=DEG`), its clock late by MS (`imudt=MS`). Two motions: "slow" (the hand-held
walk, 900 frames: 30 s, as long as the estimates take to settle) and "fast" (head turns of 150-210 deg/s with 25 ms of motion blur, 300 frames).
Each row: ATE with the IMU, ATE with vision only (the same frames, `tracker.imu=false`), their
ratio, and what the tracker measured of its IMU (summary.json `imu`) against the simulated truth:
the noise densities (gyro / accelerometer) as multiples of the true ones, the error of the
camera-IMU rotation it ended with, that of the clock offset, and the share of frames the IMU was
trusted at.

    python bench/imu_mismatch.py [--seeds 0,1] [--cases noise0.3,noise1,...] [--motions slow,fast]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MOTIONS = {"slow": "synthetic:900:imu=200", "fast": "synthetic:300:motion=turns:exposure=25:imu=200"}
CASES = {
    "noise0.3": "imunoise=0.3", "noise1": "", "noise3": "imunoise=3", "noise10": "imunoise=10",
    "rot3": "imurot=3", "rot5": "imurot=5", "dt5": "imudt=5", "dt10": "imudt=10",
}


def run(source: str, imu: bool, out: Path) -> dict:
    argv = [sys.executable, "-m", "octolog", "run", "--source", source, "--out", str(out), "--quiet", "--overwrite",
            "--rerun", "off"] + ([] if imu else ["--set", "tracker.imu=false"])
    if subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL).returncode:
        sys.exit(f"bench: {' '.join(argv)} failed")
    return json.loads((out / "summary.json").read_text())


def estimates(imu: dict, tracked: int, source: str) -> str:
    """What the tracker measured of its IMU against the simulated truth: the noise densities as
    multiples of the true ones (gyro/accelerometer), the camera-IMU rotation's error (deg), the
    clock offset's error (ms), and the share of frames the IMU was trusted at."""
    from octolog.replay.synthetic_imu import mismatch_rotation

    if not imu:
        return ""
    spec = dict(o.split("=", 1) for o in source.split(":") if "=" in o)
    scale = float(spec.get("imunoise", 1.0))
    noise = "/".join(f"{m / a / scale:.2f}" for m, a in zip(imu.get("noise_measured", [])[:2],
                                                              imu.get("noise_assumed", [])[:2]))
    truth = mismatch_rotation(float(spec.get("imurot", 0.0))).T  # camera_from_imu
    placed = np.array(imu["camera_from_imu"])[:3, :3] if imu.get("camera_from_imu") else np.eye(3)
    rot_err = np.degrees(np.arccos(np.clip((np.trace(truth.T @ placed) - 1.0) / 2.0, -1.0, 1.0)))
    late_err = imu.get("late_ms", 0.0) - float(spec.get("imudt", 0.0))
    return (f"noise x{noise or '?'} of the true, rotation off {rot_err:.2f} deg, clock off {late_err:+.1f} ms, "
            f"trusted {imu.get('trusted_frames', 0) / max(tracked, 1):.0%}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0,1", help="rooms and IMU draws")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--motions", default=",".join(MOTIONS))
    args = ap.parse_args()
    print("ATE with the IMU / vision only (cm), ratio; the IMU's estimates")
    print(f"{'motion':<6} {'seed':>4} {'case':<9} {'IMU cm':>7} {'vision cm':>9} {'ratio':>6}  estimates")
    with tempfile.TemporaryDirectory() as tmp:
        for motion in args.motions.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                base = MOTIONS[motion] + (f":seed={seed}" if seed else "")
                vision = run(base, False, Path(tmp) / "vision")["ate"]["rmse_m"] * 100
                for case in args.cases.split(","):
                    source = base + (f":{CASES[case]}" if CASES[case] else "")
                    s = run(source, True, Path(tmp) / "imu")
                    ate = s["ate"]["rmse_m"] * 100
                    est = s.get("imu") or {}
                    shown = estimates(est, s.get("tracked_frames") or s["frames"], source)
                    print(f"{motion:<6} {seed:>4} {case:<9} {ate:>7.2f} {vision:>9.2f} {ate / vision:>6.2f}  {shown}",
                          flush=True)


if __name__ == "__main__":
    main()
