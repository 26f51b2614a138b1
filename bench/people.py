"""People walking through: the map of a session with people in view against its static twin (the
same camera path and noise, no people).

    .venv/bin/python bench/people.py [--scenes cross,stand] [--octomap] [--keep DIR]

Scenes (replay/synthetic_people.py), 20 s each with the D455's depth noise and IMU:
- `cross`: two people walk to and fro across the room (seed 0's textures);
- `stand`: in another room's textures (seed 1), one person stands still in view for 5 s, then
  leaves through a door, and one walks round the room, overtaking the camera;
- `close` (not run unless named): one person walks round the pillar inside the camera's path the
  other way, filling most of the view each time they pass (a stress case).

Per run: the share of pixels people cover (mean, max, frames above 10 %), ATE and the worst pose
(cm), the dense cloud's points more than 10 cm from the room's static surfaces (ghosts), the
occupied octree voxels whose centre is more than 10 cm from them, the 2D grid's occupied cells
where people walked (their footprints, 10 cm clear of the room's objects), the voxels and cloud
points left where the person of `stand` stood (more than 10 cm from the room's surfaces), what the mapper masked
(summary.json `map.movers`: voxel hits kept out, cloud points left out), and the mapper's CPU per keyframe. The maps are put in the room's frame by
the trajectory's own alignment to the truth.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.maps import cells  # noqa: E402

from octolog.kit import metrics
from octolog.replay import synthetic_people
from octolog.replay.sources import open_source

COMMON = ":noise=d455:imu=200"
SCENES = {"cross": "synthetic:600" + COMMON + ":people=cross",
          "stand": "synthetic:600:seed=1" + COMMON + ":people=stand+round",
          "close": "synthetic:600:seed=2" + COMMON + ":people=close"}
GHOST_M = 0.10
OCTOMAP_MODEL = ["--set", "mapper.confirm_within=0", "--set", "mapper.clamp_max=0.97"]


def octolog(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "octolog", *args, "--quiet", "--overwrite"], check=True,
                   stdout=subprocess.DEVNULL)


def twin(spec: str) -> str:
    return ":".join(p for p in spec.split(":") if not p.startswith("people="))


def coverage(spec: str) -> tuple[float, float, int]:
    """The share of pixels people cover: mean, max over frames, frames above 10 %."""
    scene, static = open_source(spec).scene, open_source(twin(spec)).scene
    share = np.array([np.mean(np.any(scene.render(i).rgb != static.render(i).rgb, axis=2)) for i in range(len(scene))])
    return float(share.mean()), float(share.max()), int((share > 0.1).sum())


def occupied_centres(bt: Path) -> np.ndarray:
    """The centres of a .bt file's occupied 5 cm voxels (merged leaves expanded)."""
    occupied = [k for k, occ in cells(bt).items() if occ]
    return (np.array(occupied, dtype=float).reshape(-1, 3) + 0.5) * 0.05


def grid_cells_on_paths(folder: Path, spec: str, room_from_map: np.ndarray) -> tuple[int, int]:
    """The 2D grid's occupied cells where people walked, and how many such cells the grid knows."""
    import cv2

    meta = dict(line.split(": ", 1) for line in (folder / "map.yaml").read_text().splitlines() if ": " in line)
    res = float(meta["resolution"])
    ox, oy = (float(v) for v in meta["origin"].strip("[]").split(",")[:2])
    img = cv2.imread(str(folder / "map.pgm"), cv2.IMREAD_UNCHANGED)
    h, w = img.shape
    rows, cols = np.mgrid[0:h, 0:w]
    xy = np.stack([ox + (cols + 0.5) * res, oy + (h - 1 - rows + 0.5) * res], -1).reshape(-1, 2)
    pts = np.concatenate([xy, np.full((len(xy), 1), 1.0)], 1) @ room_from_map[:3, :3].T + room_from_map[:3, 3]
    scene = open_source(spec).scene
    walkers = scene.people
    on_path = np.zeros(len(pts), bool)
    for i in range(len(scene)):
        on_path |= synthetic_people.inside(walkers, i / 30.0, np.c_[pts[:, :2], np.full(len(pts), 0.5)])
    clear = np.ones(len(pts), bool)
    for box in scene.objects:
        clear &= ~box.contains(np.c_[pts[:, :2], np.full(len(pts), 0.3)], tol=GHOST_M)
    sel = on_path & clear
    values = img.reshape(-1)[sel]
    return int((values == 0).sum()), int((values != 205).sum())


def measure(folder: Path, spec: str) -> dict:
    s = json.loads((folder / "summary.json").read_text())
    est, gt = metrics.read_tum(folder / "trajectory.txt"), metrics.read_tum(folder / "groundtruth.txt")
    ate = metrics.ate(est, gt)
    map_from_world = np.array(json.loads((folder / "map_stats.json").read_text())["map_from_world"])
    room_from_map = ate.alignment @ np.linalg.inv(map_from_world)
    scene = open_source(spec).scene

    def off(p: np.ndarray) -> np.ndarray:
        return scene.distance_to_surface(p @ room_from_map[:3, :3].T + room_from_map[:3, 3])

    import open3d as o3d

    cloud = np.asarray(o3d.io.read_point_cloud(str(folder / "cloud.ply")).points)
    voxels = occupied_centres(folder / "map.bt")
    stood = "-"
    if "stand" in spec.split("people=")[-1]:  # where the person stood for 5 s, once they have left
        def left(p: np.ndarray) -> int:
            room = p @ room_from_map[:3, :3].T + room_from_map[:3, 3]
            there = synthetic_people.inside(synthetic_people.crowd("stand"), 2.5, room, margin_m=0.05)
            return int((there & (off(p) > GHOST_M)).sum())
        stood = f"{left(voxels)} / {left(cloud)}"
    grid_ghosts, grid_known = grid_cells_on_paths(folder, spec, room_from_map)
    mapper_s = s["cpu_s"]["mapper"]["buckets"].get("mapper", 0.0)
    return {"ate": ate.rmse, "worst": ate.max, "cloud": len(cloud), "cloud_ghosts": int((off(cloud) > GHOST_M).sum()),
            "voxels": len(voxels), "voxel_ghosts": int((off(voxels) > GHOST_M).sum()), "grid_ghosts": grid_ghosts,
            "grid_known": grid_known, "movers": s["map"].get("movers", {}),
            "ms_per_kf": 1000 * mapper_s / max(s["map"]["keyframes"], 1), "keyframes": s["map"]["keyframes"],
            "stood": stood}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="cross,stand")
    ap.add_argument("--keep", help="keep the session folders here")
    ap.add_argument("--octomap", action="store_true",
                    help="also map the people with OctoMap's model (every end point at once, clamp 0.97)")
    args = ap.parse_args()
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="octolog-people-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"sessions in {root}")
    print("| scene | run | people cover (mean / max / frames > 10 %) | ATE, cm | worst, cm | cloud ghosts | "
          "octree ghost voxels | grid cells occupied on paths (of known) | where one stood 5 s: voxels / points | "
          "masked voxels / cleared cloud points | mapper ms / keyframe |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.scenes.split(","):
        spec = SCENES[name]
        cover = coverage(spec)
        runs = [("people", spec, []), ("twin", twin(spec), [])]
        if args.octomap:
            runs.append(("people, OctoMap's model", spec, OCTOMAP_MODEL))
        for label, src, sets in runs:
            folder = root / f"{name}-{label.split(',')[0]}{'-octomap' if sets else ''}"
            octolog("run", "--source", src, "--out", str(folder), *sets)
            m = measure(folder, spec)
            share = (f"{cover[0] * 100:.1f} % / {cover[1] * 100:.0f} % / {cover[2]}" if label == "people" else "-")
            masked = f"{m['movers']['masked_voxels']} / {m['movers']['cleared_points']}" if m["movers"] else "-"
            print(f"| {name} | {label} | {share} | {m['ate'] * 100:.2f} | {m['worst'] * 100:.2f} | "
                  f"{m['cloud_ghosts'] / max(m['cloud'], 1) * 100:.3f} % ({m['cloud_ghosts']}) | {m['voxel_ghosts']} | "
                  f"{m['grid_ghosts']} ({m['grid_known']}) | {m['stood']} | {masked} | {m['ms_per_kf']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
