"""How the mapper's cost per keyframe and its memory grow with the mapped floor.

The synthetic room (6 x 5 m) walked once, every `--every`-th frame a keyframe at its ground-truth
pose, is laid down again and again side by side on a grid (8 m apart), each copy a new stretch of
floor, through the whole mapper (`mapper/core.py: Mapper.integrate` with `octolog map`'s defaults:
5 cm voxels with free space, colour, the dense cloud; the grid is not redrawn per keyframe here).
Per step of floor: mapped floor area, keyframes so far, the median and p90 ms per keyframe over the
last room laid down, voxels known, the voxel store's and the process's memory.

    python bench/mapper_growth.py [--rooms 1,4,34] [--frames 300] [--every 15]
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import numpy as np

from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.replay.synthetic import SyntheticScene
from octolog.replay.synthetic_room import ROOM_SIZE_M

SPACING_M = 8.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rooms", default="1,4,34", help="report after this many rooms (30 m^2 each)")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--every", type=int, default=15)
    args = ap.parse_args()
    marks = sorted(int(r) for r in args.rooms.split(","))
    frames, poses = room_keyframes(args.frames, args.every)
    mapper = make_mapper(MapperConfig())
    side = math.ceil(math.sqrt(marks[-1]))
    room_m2 = ROOM_SIZE_M[0] * ROOM_SIZE_M[1]
    print(f"synthetic room ({room_m2:g} m^2), {len(frames)} keyframes per room, rooms {SPACING_M:g} m apart")
    print("| rooms | floor, m² | keyframes | ms/keyframe median / p90 (last room) | voxels known | voxel store, MB | "
          "process peak RSS, MB |")
    print("|---|---|---|---|---|---|---|")
    kid = 0
    for room in range(marks[-1]):
        shift = room_shift(room, side)
        ms = []
        for frame, pose in zip(frames, poses):
            t = time.perf_counter()
            mapper.integrate(kid, shift @ pose, frame)
            ms.append((time.perf_counter() - t) * 1e3)
            kid += 1
        if room + 1 in marks:
            st = mapper.octree.stats()
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(f"| {room + 1} | {(room + 1) * room_m2:.0f} | {kid} | {np.median(ms):.1f} / "
                  f"{np.percentile(ms, 90):.1f} | {st['occupied_voxels'] + st['free_voxels']} | "
                  f"{st['memory_bytes'] / 2**20:.0f} | {rss:.0f} |", flush=True)


def room_keyframes(n_frames: int, every: int) -> tuple[list, list]:
    """The synthetic room's every `every`-th frame of `n_frames`, and its ground-truth pose."""
    scene = SyntheticScene(n_frames=n_frames)
    return [scene.render(i) for i in range(0, n_frames, every)], scene.poses()[::every]


def room_shift(room: int, side: int) -> np.ndarray:
    """Where copy `room` of the room lies: on a grid `side` rooms wide, SPACING_M apart on the floor."""
    shift = np.eye(4)
    shift[0, 3], shift[2, 3] = SPACING_M * (room % side), SPACING_M * (room // side)  # x and z: the floor
    return shift


if __name__ == "__main__":
    main()
