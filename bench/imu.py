"""RGB-D-inertial against RGB-D only, side by side, through `octolog run` (the real processes, the
bus, the session log and Rerun recordings on, as a user runs it).

Each case runs twice: with the IMU (the default) and with `tracker.imu=false`. Paced at the
camera's rate with the live tracker (`replay.rate=1`, `tracker.live=true`; `--lockstep`: every
frame, unpaced). Per run, from its session log and summary: frames LOST, INERTIAL and SKIPPED, ATE
against the ground truth, the tracker's wall ms per frame (median, p90), for a case with a
textureless stretch (`blank=AT+S`) the largest position drift over it relative to the last pose
before it, and how far from level the map stands (the angle between its up and the room's true
up seen from each tracked frame's estimated pose, averaged; with the IMU the map's up is the
tracker's estimate, without it the accelerometer's mean at the first frame, each levelled on a
horizontal plane of the first frame when it has one).

Cases (the synthetic room with its simulated D455 IMU at 200 Hz, 30 fps):
- turns: fast head turns (150-210 deg/s) with 10 ms of motion blur; turns25: 25 ms (heavy blur)
- blank: the slow walk, the camera seeing no texture for 1.5 s from 3 s
- slow: the slow walk; `seed=N` suffixes give another room and another draw of the IMU's noise

    python bench/imu.py [--cases turns,turns25,blank,slow] [--seeds 0,1] [--lockstep]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
CASES = {
    "turns": "synthetic:300:motion=turns:exposure=10:imu=200",
    "turns25": "synthetic:300:motion=turns:exposure=25:imu=200",
    "blank": "synthetic:180:imu=200:blank=3+1.5",
    "slow": "synthetic:300:imu=200",
}


def run(source: str, imu: bool, out: Path, lockstep: bool) -> dict:
    from octolog.kit.mcaplog import read_wire
    from octolog.schemas import codec, topics

    argv = [sys.executable, "-m", "octolog", "run", "--source", source, "--out", str(out), "--quiet", "--overwrite"]
    sets = ([] if imu else ["tracker.imu=false"]) + ([] if lockstep else ["replay.rate=1", "tracker.live=true"])
    for s in sets:
        argv += ["--set", s]
    if subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL).returncode:
        sys.exit(f"bench: {' '.join(argv)} failed")
    counts = {"LOST": 0, "INERTIAL": 0, "SKIPPED": 0}
    ms = []
    for m in read_wire(out / "session.mcap", [topics.TRACKING_STATUS.name]):
        st = codec.decode(m.data, topics.TRACKING_STATUS.msgtype)
        for name in counts:
            counts[name] += st.state == getattr(st, name)
        if st.state != st.SKIPPED:
            ms.append(st.processing_ms)
    summary = json.loads((out / "summary.json").read_text())
    return {**counts, "ate_cm": summary["ate"]["rmse_m"] * 100, "ms_med": statistics.median(ms),
            "ms_p90": float(np.percentile(ms, 90)), "drift_cm": stretch_drift(out, source) * 100,
            "up_deg": up_error_deg(out, source), "imu": summary.get("imu")}


def up_error_deg(out: Path, source: str) -> float:
    """How far from level the map stands, where the camera went: the angle between the map frame's
    up (config.toml's `mapper.grid_up`, in `world`) and the room's true up as each tracked frame's
    estimated pose puts it into `world`, averaged over the frames (a tracker whose attitude drifted
    has no single right up; at frame 0 it is the first camera's true up)."""
    import tomllib

    from octolog.kit.metrics import read_tum
    from octolog.replay.sources import open_source

    up = np.asarray(tomllib.loads((out / "config.toml").read_text())["mapper"]["grid_up"], float)
    up = up / np.linalg.norm(up)
    scene = open_source(source).scene
    seq = {scene.stamp_ns(i): i for i in range(len(scene))}
    est = read_tum(out / "trajectory.txt")
    angles = []
    for k, stamp in enumerate(est.stamps_ns.tolist()):
        seen = Rotation.from_quat(est.quats_xyzw[k]).as_matrix() @ scene.pose(seq[stamp])[:3, :3].T @ [0.0, 0.0, 1.0]
        angles.append(np.degrees(np.arccos(np.clip(up @ seen, -1.0, 1.0))))
    return float(np.mean(angles))


def stretch_drift(out: Path, source: str) -> float:
    """Largest position error over the `blank=AT+S` stretch, relative to the last pose before it (nan: none)."""
    from octolog.kit.metrics import read_tum

    spec = dict(o.split("=", 1) for o in source.split(":") if "=" in o)
    if "blank" not in spec:
        return float("nan")
    at, length = (float(v) for v in spec["blank"].split("+"))
    est, gt = read_tum(out / "trajectory.txt"), read_tum(out / "groundtruth.txt")
    rel = (est.stamps_ns - gt.stamps_ns[0]) * 1e-9
    before = np.flatnonzero(rel < at)
    during = np.flatnonzero((rel >= at) & (rel < at + length))
    if not before.size or not during.size:
        return float("nan")
    g = {int(s): k for k, s in enumerate(gt.stamps_ns)}

    def T(tr, k):
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = Rotation.from_quat(tr.quats_xyzw[k]).as_matrix(), tr.positions[k]
        return M

    b = int(before[-1])
    return max(float(np.linalg.norm((np.linalg.inv(T(est, b)) @ T(est, k))[:3, 3]
                                    - (np.linalg.inv(T(gt, g[int(est.stamps_ns[b])])) @ T(gt, g[int(est.stamps_ns[k])]))[:3, 3]))
               for k in during)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="turns,turns25,blank,slow")
    ap.add_argument("--seeds", default="0,1", help="room and IMU noise seeds per case")
    ap.add_argument("--lockstep", action="store_true", help="every frame, unpaced (default: paced at 30 fps, live)")
    args = ap.parse_args()
    mode = "lockstep" if args.lockstep else "paced at 30 fps, live tracker"
    print(f"octolog run, {mode}; with the IMU | RGB-D only")
    print(f"{'case':<18} {'LOST':>9} {'INERTIAL':>9} {'SKIPPED':>9} {'ATE cm':>13} {'drift cm':>13} "
          f"{'ms median':>13} {'ms p90':>13} {'up err deg':>13}")
    for case in args.cases.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            source = CASES[case] + (f":seed={seed}" if seed else "")
            with tempfile.TemporaryDirectory() as tmp:
                a, b = (run(source, imu, Path(tmp) / ("imu" if imu else "rgbd"), args.lockstep) for imu in (True, False))
            name = f"{case} seed {seed}"

            def pair(key: str, fmt: str) -> str:
                return f"{format(a[key], fmt)} | {format(b[key], fmt)}"
            print(f"{name:<18} {pair('LOST', 'd'):>9} {pair('INERTIAL', 'd'):>9} {pair('SKIPPED', 'd'):>9} "
                  f"{pair('ate_cm', '.2f'):>13} {pair('drift_cm', '.2f'):>13} {pair('ms_med', '.1f'):>13} "
                  f"{pair('ms_p90', '.1f'):>13} {pair('up_deg', '.2f'):>13}")
            if a["imu"]:
                bg = np.degrees(a["imu"]["gyro_bias"])
                print(f"{'':<18} gyro bias estimate {np.round(bg, 3).tolist()} deg/s")


if __name__ == "__main__":
    main()
