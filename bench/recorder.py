"""Recorder throughput at the D455 default profile (colour 1280x720@30, aligned depth 848x480@30
registered to colour, gyro 200 Hz, accel 100 Hz) through pyrealsense2's software device.

For every colour codec x depth codec x chunk compression: a paced run (the simulated camera
pushes on its own clock, like a real one; frames the recorder cannot take are lost and counted)
gives drops, CPU and write rate; an on-demand run gives the highest frame rate the recorder
sustains (headroom). Beside them: a plain write() of the same bytes to the same disk, with and
without fsync, as the physical limit, and the CPU the simulated source itself costs.

    python bench/recorder.py --seconds 20 [--dir /tmp/bench] [--only jpeg/png/lz4]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from octolog.recorder import node  # noqa: E402
from octolog.recorder.config import RecorderConfig, SoftwareConfig, capture_profile  # noqa: E402
from octolog.recorder.frame_converter import FrameConverter  # noqa: E402
from octolog.recorder.software_d455 import SoftwareDeviceBackend  # noqa: E402


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def recording(cfg: RecorderConfig, out: Path) -> dict:
    t0, c0 = time.perf_counter(), cpu_s()
    res = node.run(cfg, out, overwrite=True)
    wall, cpu = time.perf_counter() - t0, cpu_s() - c0
    span = (res.last_stamp_ns - res.first_stamp_ns) / 1e9 or 1e-9
    return {"frames": res.streams["color"].frames, "dropped": res.dropped, "cpu": 100 * cpu / wall,
            "mb_s": res.bytes / 1e6 / span, "gb_min": res.bytes / 1e9 / span * 60, "wall": wall,
            "bytes": res.bytes, "paths": res.paths,
            "per_stream": {s: {k: v for k, v in (("gaps", st.device_gaps), ("queue", st.queue_drops),
                                                  ("unpaired", st.unpaired)) if v}
                           for s, st in res.streams.items() if st.dropped}}


def source_only(seconds: float) -> float:
    """CPU % of the paced software device plus frame conversion (alignment), nothing written."""
    b = SoftwareDeviceBackend(frames=int(seconds * 30), paced=True)
    cfg = RecorderConfig()
    b.open(capture_profile(cfg))
    conv = FrameConverter(align=True, raw_depth=False, fps=30)
    t0, c0 = time.perf_counter(), cpu_s()
    while (frames := b.wait(0.1)) is not None:
        for f in frames:
            conv.convert(f)
    cpu = 100 * (cpu_s() - c0) / (time.perf_counter() - t0)
    b.close()
    return cpu


def plain_write(src: Path, dst: Path, *, fsync: bool) -> float:
    """MB/s of os.write() of src's bytes in 4 MB blocks to dst (the same disk)."""
    data = src.read_bytes()
    block = 4 << 20
    fd = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    t0 = time.perf_counter()
    for i in range(0, len(data), block):
        os.write(fd, data[i:i + block])
    if fsync:
        os.fsync(fd)
    dt = time.perf_counter() - t0
    os.close(fd)
    dst.unlink()
    return len(data) / 1e6 / dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="sensor seconds per paced run (default 60)")
    ap.add_argument("--max-fps-frames", type=int, default=150, help="frames for the on-demand run (0: skip)")
    ap.add_argument("--dir", default=None, help="where to write (default: a temporary folder)")
    ap.add_argument("--only", default=None, help="one combination, e.g. jpeg/png/lz4")
    args = ap.parse_args()
    work = Path(args.dir or tempfile.mkdtemp(prefix="octolog-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    combos = [(c, d, z) for c in ("jpeg", "raw") for d in ("png", "raw") for z in ("lz4", "zstd", "none")]
    if args.only:
        combos = [tuple(args.only.split("/"))]  # type: ignore[list-item]
    base = RecorderConfig(backend="software")
    print(f"# recorder bench: {platform.node()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"disk {work} ({shutil.disk_usage(work).free / 1e9:.0f} GB free)")
    print(f"# D455 default profile + IMU (gyro 200 Hz, accel 100 Hz), aligned depth, {args.seconds:.0f} s sensor time"
          f" per paced run; CPU in % of one core (machine: {100 * (os.cpu_count() or 1)} %)")
    src_cpu = source_only(min(args.seconds, 10.0))
    print(f"# the simulated camera alone (software device + syncer + align, no writing): {src_cpu:.0f} % CPU")
    print()
    head = (f"| {'colour':6} | {'depth':5} | {'chunks':6} | {'frames':>6} | {'dropped':>7} | {'CPU %':>5} | "
            f"{'MB/s':>6} | {'GB/min':>6} | {'max fps':>7} | {'write() MB/s':>12} | {'+fsync MB/s':>11} |")
    print(head)
    print("|" + "|".join("-" * (len(c)) for c in head.split("|")[1:-1]) + "|")
    for color, depth, comp in combos:
        cfg = replace(base, color_codec=color, depth_codec=depth, compression=comp)
        paced = replace(cfg, software=SoftwareConfig(frames=int(args.seconds * 30), paced=True))
        out = work / f"bench_{color}_{depth}_{comp}.mcap"
        r = recording(paced, out)
        w_cache = plain_write(out, work / "plain.bin", fsync=False)
        w_sync = plain_write(out, work / "plain.bin", fsync=True)
        out.unlink()
        max_fps = float("nan")
        if args.max_fps_frames:
            fast = replace(cfg, software=SoftwareConfig(frames=args.max_fps_frames, paced=False))
            q = recording(fast, out)
            max_fps = q["frames"] / q["wall"]
            out.unlink()
        drops = f"{r['dropped']}" + (f" {r['per_stream']}" if r["dropped"] else "")
        print(f"| {color:6} | {depth:5} | {comp:6} | {r['frames']:6d} | {drops:>7} | {r['cpu']:5.0f} | "
              f"{r['mb_s']:6.1f} | {r['gb_min']:6.2f} | {max_fps:7.1f} | {w_cache:12.0f} | {w_sync:11.0f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
