"""What splitting the map across mapper shards buys: per shard, the keyframes it makes clouds for,
its time per keyframe, its CPU and its memory, against one mapper for the whole floor.

The synthetic room laid down side by side as in bench/mapper_growth.py (`--rooms` copies, 8 m
apart, 20 keyframes each at ground-truth poses), each mapper (the whole map, then shard 1..N of
`--shards`, `mapper.tile_m` = `--tile-m`) in a process of its own, so each peak RSS is its own.
Each writes its map files; the shards are then stitched and compared with the whole map's bytes.

    python bench/mapper_shards.py [--rooms 16] [--shards 4] [--tile-m 16]
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

FILES = ("map.bt", "map.ot", "cloud.ply", "map.pgm")


def one(rooms: int, shard: str, tile_m: float, out: Path) -> dict:
    """One mapper over the layout (run in a child process): its figures."""
    from mapper_growth import room_keyframes, room_shift

    from octolog.mapper.config import MapperConfig
    from octolog.mapper.core import make_mapper
    from octolog.mapper.shards import write_shard

    frames, poses = room_keyframes(300, 15)
    mapper = make_mapper(MapperConfig(shard=shard, tile_m=tile_m))
    side = math.ceil(math.sqrt(rooms))
    ms, kid = [], 0
    cpu0 = time.process_time()
    for room in range(rooms):
        shift = room_shift(room, side)
        for frame, pose in zip(frames, poses):
            t = time.perf_counter()
            mapper.integrate(kid, shift @ pose, frame)
            ms.append((time.perf_counter() - t) * 1e3)
            kid += 1
    cpu = time.process_time() - cpu0
    t = time.perf_counter()
    mapper.write(out)
    if shard:
        write_shard(mapper, out)
    st = mapper.octree.stats()
    return {"keyframes": kid, "built": sum(kf.points_cam is not None for kf in mapper.keyframes.values()),
            "median": float(np.median(ms)), "mean": float(np.mean(ms)), "cpu_s": cpu,
            "write_s": time.perf_counter() - t, "voxels": st["occupied_voxels"] + st["free_voxels"],
            "cloud": len(mapper.cloud.cloud()[0]),
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rooms", type=int, default=16)
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--tile-m", type=float, default=16.0)
    ap.add_argument("--child", nargs=2, metavar=("SHARD", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one(args.rooms, args.child[0], args.tile_m, Path(args.child[1]))))
        return
    from octolog.mapper.shards import stitch

    tmp = Path(tempfile.mkdtemp(prefix="octolog-shards-"))
    rows = {}
    for shard in ["", *(f"{k}/{args.shards}" for k in range(1, args.shards + 1))]:
        out = tmp / (shard.replace("/", "of") or "whole")
        done = subprocess.run([sys.executable, __file__, "--rooms", str(args.rooms), "--tile-m", str(args.tile_m),
                               "--child", shard, str(out)], capture_output=True, text=True, check=True)
        rows[shard] = json.loads(done.stdout.splitlines()[-1])
    t = time.perf_counter()
    stitch([tmp / f"{k}of{args.shards}" for k in range(1, args.shards + 1)], tmp / "stitched")
    stitch_s = time.perf_counter() - t
    same = all((tmp / "stitched" / f).read_bytes() == (tmp / "whole" / f).read_bytes() for f in FILES)
    whole = rows[""]
    print(f"{args.rooms} rooms ({args.rooms * 30} m^2), {whole['keyframes']} keyframes, {args.tile_m:g} m tiles, "
          f"{args.shards} shards; stitched in {stitch_s:.1f} s, same bytes as the whole map: {same}")
    print("| mapper | clouds made | ms per keyframe, median / mean | CPU, s | voxels | cloud points | peak RSS, MB |")
    print("|---|---|---|---|---|---|---|")
    for shard, r in rows.items():
        print(f"| {'shard ' + shard if shard else 'whole map'} | {r['built']} | {r['median']:.1f} / {r['mean']:.1f} | "
              f"{r['cpu_s']:.0f} | {r['voxels'] / 1e6:.2f} M | {r['cloud'] / 1e6:.2f} M | {r['rss_mb']:.0f} |")


if __name__ == "__main__":
    main()
