"""Coming back to a map: TUM fr1/xyz first300 split in two sessions recorded apart.

    OCTOLOG_DATA=../shared/data python bench/prior_map.py [--split 150] [--keep DIR]

Runs `octolog run` four times: the whole sequence (the reference), the first part (frames before
`--split`), then the rest twice with `--map` of the first part's session, mapping
(`tracker.mode=map`, the default) and localizing only (`tracker.mode=localize`). Prints, per run:
the frame the camera was found at in the saved map, ATE with the first part's own alignment to the
ground truth (no new alignment: the trajectory must land in the first session's world) next to
the reference run's frames after the split under the alignment of its own first part, the
tracker's ms per frame (median, p90, from its status messages), the map's agreement with the
reference run's (occupied voxels with an occupied voxel within one voxel in the other map), and
whether the first session's files are byte-identical afterwards.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from octolog.kit import metrics
from octolog.kit.mcaplog import read_wire
from octolog.schemas import codec
from octolog.schemas.topics import TRACKING_STATUS


def octolog(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "octolog", *args, "--quiet"], check=True, stdout=subprocess.DEVNULL)


def aligned_ate(traj: metrics.Trajectory, gt: metrics.Trajectory, alignment: np.ndarray) -> float:
    """ATE RMSE (m) of `traj` under a given alignment (gt ~= alignment @ est)."""
    e, g = metrics._pairs(traj, gt, metrics.DEFAULT_MAX_DT_NS)
    err = np.linalg.norm(g.positions - (e.positions @ alignment[:3, :3].T + alignment[:3, 3]), axis=1)
    return float(np.sqrt(np.mean(err ** 2)))


def tracker_ms(folder: Path) -> tuple[float, float]:
    ms = [codec.decode(m.data, m.msgtype).processing_ms for m in read_wire(folder / "session.mcap", [TRACKING_STATUS.name])]
    ms = [v for v in ms if v > 0]
    return float(np.median(ms)), float(np.percentile(ms, 90))


def occupied(bt: Path) -> set[tuple[int, int, int]]:
    import pyoctomap  # the reference reader of .bt files

    tree = pyoctomap.OcTree(0.05)
    tree.readBinary(str(bt))
    cells = set()
    for it in tree.begin_leafs():
        if not tree.isNodeOccupied(it):
            continue
        k = round(it.getSize() / 0.05)
        low = np.floor((np.array(it.getCoordinate()) - it.getSize() / 2) / 0.05 + 0.5).astype(int)
        cells.update((low[0] + i, low[1] + j, low[2] + m) for i in range(k) for j in range(k) for m in range(k))
    return cells


def near_share(a: set, b: set) -> float:
    """Of `a`'s occupied voxels, the share with one of `b`'s within one voxel."""
    near = list(itertools.product((-1, 0, 1), repeat=3))
    return sum(any((c[0] + i, c[1] + j, c[2] + k) in b for i, j, k in near) for c in a) / max(len(a), 1)


def digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", type=int, default=150)
    ap.add_argument("--keep", help="keep the session folders here")
    args = ap.parse_args()
    data = Path(os.environ.get("OCTOLOG_DATA", "../shared/data"))
    seq = f"tum:{data / 'tum' / 'rgbd_dataset_freiburg1_xyz_first300'}"
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="octolog-prior-"))
    root.mkdir(parents=True, exist_ok=True)
    whole, first, mapping, localize = (root / n for n in ("whole", "first", "second-map", "second-localize"))
    octolog("run", "--source", seq, "--out", str(whole), "--overwrite")
    octolog("run", "--source", seq, "--out", str(first), "--overwrite", "--set", f"replay.end={args.split}")
    before = digest(first)
    octolog("run", "--source", seq, "--out", str(mapping), "--overwrite", "--set", f"replay.start={args.split}",
            "--map", str(first))
    unchanged_map = digest(first) == before
    octolog("run", "--source", seq, "--out", str(localize), "--overwrite", "--set", f"replay.start={args.split}",
            "--map", str(first), "--set", "tracker.mode=localize")
    unchanged_localize = digest(first) == before

    gt = metrics.read_tum(whole / "groundtruth.txt")
    ref = metrics.read_tum(whole / "trajectory.txt")
    n_first = len(metrics.read_tum(first / "trajectory.txt"))
    ref_first = metrics.ate(ref.subset(np.arange(n_first)), gt)
    ref_rest = aligned_ate(ref.subset(np.arange(n_first, len(ref))), gt, ref_first.alignment)
    own = metrics.ate(metrics.read_tum(first / "trajectory.txt"), gt)
    ref_cells = occupied(whole / "map.bt")
    print(f"TUM fr1/xyz first300 split at frame {args.split}; sessions in {root}")
    print(f"whole run: ATE {metrics.ate(ref, gt).rmse * 100:.3f} cm; its frames from {args.split} under the alignment "
          f"of its frames before: {ref_rest * 100:.3f} cm")
    print(f"first part: ATE {own.rmse * 100:.3f} cm; first session's files byte-identical after the mapping run: "
          f"{unchanged_map}, after the localize run: {unchanged_localize}")
    print("| second part | found at frame | ATE, first part's alignment, cm | / whole run's | tracker ms/frame median, p90 "
          "| keyframes | occupied voxels near the whole run's, both ways |")
    print("|---|---|---|---|---|---|---|")
    for name, folder in (("map", mapping), ("localize", localize)):
        import json

        summary = json.loads((folder / "summary.json").read_text())
        ate = aligned_ate(metrics.read_tum(folder / "trajectory.txt"), gt, own.alignment)
        med, p90 = tracker_ms(folder)
        cells = occupied(folder / "map.bt")
        print(f"| {name} | {summary['prior_map']['found_at_frame']} | {ate * 100:.3f} | {ate / ref_rest:.2f}x | "
              f"{med:.1f}, {p90:.1f} | {summary['map']['keyframes']} | "
              f"{near_share(cells, ref_cells) * 100:.1f} % / {near_share(ref_cells, cells) * 100:.1f} % |", flush=True)


if __name__ == "__main__":
    main()
