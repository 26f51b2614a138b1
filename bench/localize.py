"""Localizing in yesterday's map: pairs of synthetic sessions through the same room, the second
from another place, walking the other way round, and out of the first one's map and back.

    .venv/bin/python bench/localize.py [--pairs 1,2] [--keep DIR]

Each pair: session A walks 12 s (two thirds of the loop round the pillar); session B starts in
the middle of A's stretch, walks 18 s the other way round: 9 s through A's stretch, 6 s where A
never was, 3 s in A's stretch again. Pair 2 is the same in another room's textures and starts
elsewhere on the loop. Both with the D455's depth noise and IMU. B runs three times:
- alone (SLAM in its own world): its own ATE, fitted to the truth;
- `--map A --set tracker.mode=localize`;
- `--map A` (SLAM on A's map).
The localize and map runs are measured in A's world: their poses under A's own alignment to the
truth, no new fit. Prints, per run: the frames with a pose (as published live, and in
trajectory.txt, where frames tracked before the camera was found in A's map are placed after),
the ATE there and the worst pose, the same of the poses as they were published (before the back
end's later corrections and the final adjustment), against B's own-fit ATE and A's, the real-time factor (B's
camera time over the run's wall time), and the summary's counts (`prior_map`); per pair, how far
A's map points stand off the room's true surfaces (what bounds a session placed in A's world).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from octolog.kit import metrics
from octolog.kit.geometry import matrices_to_quats
from octolog.kit.mcaplog import read_wire
from octolog.schemas import codec, posemsgs
from octolog.replay.sources import open_source
from octolog.schemas.topics import POSE, TRACKING_STATUS
from octolog.tracker.mapfile import load_map

LOST = 2  # TrackingStatus.state (tracker/interface.py)

COMMON = ":noise=d455:imu=200"
PAIRS = {  # name: (session A, session B)
    "1": ("synthetic:360" + COMMON, "synthetic:540:start=9:reverse=1" + COMMON),
    "2": ("synthetic:360:start=9:seed=1" + COMMON, "synthetic:540:reverse=1:seed=1" + COMMON),
}


def octolog(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "octolog", *args, "--quiet", "--overwrite"], check=True,
                   stdout=subprocess.DEVNULL)


def summary(folder: Path) -> dict:
    return json.loads((folder / "summary.json").read_text())


def map_error(session: Path, source: str, alignment: np.ndarray) -> tuple[float, float]:
    """How far the saved map's good points stand off the room's true surfaces (median, p90, m)."""
    saved = load_map(session)
    n = saved.points.size
    xyz = saved.points.xyz[:n][~saved.points.bad[:n]]
    d = np.abs(open_source(source).scene.distance_to_surface(xyz @ alignment[:3, :3].T + alignment[:3, 3]))
    return float(np.median(d)), float(np.percentile(d, 90))


def _ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def live(folder: Path) -> tuple[float, metrics.Trajectory]:
    """The share of frames the tracker published a pose for as they came (not LOST), and those
    poses as published (before any later correction)."""
    log = folder / "session.mcap"
    states = {_ns(m.header): m.state for m in (codec.decode(r.data, r.msgtype) for r in read_wire(log, [TRACKING_STATUS.name]))}
    kept = [(_ns(m.header), posemsgs.pose_matrix(m.pose)) for m in (codec.decode(r.data, r.msgtype) for r in read_wire(log, [POSE.name]))
            if states.get(_ns(m.header), LOST) != LOST]
    T = np.array([t for _, t in kept]).reshape(-1, 4, 4)
    traj = metrics.Trajectory(np.array([n for n, _ in kept], np.int64), T[:, :3, 3], matrices_to_quats(T[:, :3, :3]))
    return sum(v != LOST for v in states.values()) / max(len(states), 1), traj


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", default=",".join(PAIRS))
    ap.add_argument("--keep", help="keep the session folders here")
    args = ap.parse_args()
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="octolog-localize-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"sessions in {root}")
    print("| pair | B run | poses live / in trajectory.txt | ATE in A's world, cm | worst, cm | / B's own | / A's own "
          "| live poses: ATE, worst, cm | real-time factor | found at | localized / carried / lost / relocalised |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.pairs.split(","):
        a_src, b_src = PAIRS[name]
        a, alone, loc, slam = (root / f"{name}-{n}" for n in ("A", "B-alone", "B-localize", "B-map"))
        octolog("run", "--source", a_src, "--out", str(a))
        octolog("run", "--source", b_src, "--out", str(alone))
        octolog("run", "--source", b_src, "--out", str(loc), "--map", str(a), "--set", "tracker.mode=localize")
        octolog("run", "--source", b_src, "--out", str(slam), "--map", str(a))
        a_ate = metrics.ate(metrics.read_tum(a / "trajectory.txt"), metrics.read_tum(a / "groundtruth.txt"))
        gt_b = metrics.read_tum(alone / "groundtruth.txt")
        own = metrics.ate(metrics.read_tum(alone / "trajectory.txt"), gt_b).rmse
        for label, folder in (("alone", alone), ("localize", loc), ("map", slam)):
            s = summary(folder)
            traj = metrics.read_tum(folder / "trajectory.txt")
            res = metrics.ate(traj, gt_b) if folder is alone else metrics.ate_in(traj, gt_b, a_ate.alignment)
            share, published = live(folder)
            now = metrics.ate(published, gt_b) if folder is alone else metrics.ate_in(published, gt_b, a_ate.alignment)
            prior = s.get("prior_map") or {}
            tally = " / ".join(str(prior.get(k, "-")) for k in ("localized", "carried", "lost", "relocalised"))
            found = "dropped" if prior.get("dropped") else prior.get("found_at_frame", "-")
            rtf = (len(gt_b) - 1) / 30.0 / s["wall_s"]
            print(f"| {name} | {label} | {share * 100:.1f} % / {res.n_pairs / len(gt_b) * 100:.1f} % | "
                  f"{res.rmse * 100:.2f} | {res.max * 100:.2f} | {res.rmse / own:.2f}x | {res.rmse / a_ate.rmse:.2f}x | "
                  f"{now.rmse * 100:.2f}, {now.max * 100:.2f} | {rtf:.2f} | {found} | {tally} |", flush=True)
        med, p90 = map_error(a, a_src, a_ate.alignment)
        print(f"pair {name}: A's own ATE {a_ate.rmse * 100:.2f} cm, B's own {own * 100:.2f} cm; A's map points off "
              f"the room's surfaces: median {med * 100:.2f} cm, p90 {p90 * 100:.2f} cm", flush=True)


if __name__ == "__main__":
    main()
