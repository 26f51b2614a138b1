"""End-to-end pipeline benchmark: `octolog run` as a user runs it, on slow and fast motion at 30 fps.

For each motion case (bench/devdata.py: TUM fr1/xyz first300 as recorded; the same every 3rd
frame re-timed to 30 fps; the synthetic room with 150-210 deg/s head turns, blur and Kinect depth
noise), runs `octolog run` with its default outputs (session log and Rerun recordings on):

- lockstep (`--repeat` runs): frames as fast as the pipeline takes them, with one queued on purpose
  (`replay.window=2`), against the same tracker and mapper cores in one process (frames decoded as
  read, no transport, no logging) as the reference;
- live (`--live` runs): paced at the camera's rate (`replay.rate=1`) with the live tracker
  (`tracker.live=true`: when behind it skips frames, on record): frames skipped and the
  frame->pose latency a camera sees (the target: p90 <= 66 ms, two frames at 30 fps);
- where the CPU goes: milliseconds of CPU per camera frame by stage while frames stream (replay,
  decode, features, tracking, back end, mapper, session log, Rerun, the rest), against the 66.7 ms
  two cores have per frame at 30 fps. Process CPU is sampled from /proc (10 Hz) and read at the
  first frame and at the last pose; the tracker's split comes from its own thread clocks
  (kit/cpuclock.py, summary.json `cpu_s`);
- what the tracker published: frames LOST, and published consecutive poses more than 5 cm off the
  ground truth's step (what the mapper integrated; bench/devdata.py: published_steps).

    python bench/pipeline.py [--cases first300,first300x3,turns] [--repeat 3] [--live 1]

Figures: real-time factor = sequence seconds / wall seconds, "streaming" from the first frame on
the bus to the last frame's pose, "whole run" with start-up and end of stream (final bundle
adjustment, map files); tracker ms/frame = TrackingStatus.processing_ms; frame->pose latency =
session log's receipt of a frame to its receipt of that frame's status; mapper ms/keyframe =
MapUpdate.processing_ms; ATE on the final trajectory (trajectory.txt).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from devdata import CASES, case_source, open_case, published_steps  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BUDGET_MS = 2 * 1000 / 30  # two cores, 30 frames a second
TICK = os.sysconf("SC_CLK_TCK")


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


class CpuSampler(threading.Thread):
    """CPU seconds of a process tree, by stage, sampled from /proc every `period_s`."""

    def __init__(self, root: int, period_s: float = 0.1) -> None:
        super().__init__(daemon=True)
        self.root, self.period_s = root, period_s
        self.samples: list[tuple[int, dict[str, float]]] = []  # (time ns, role -> CPU s)
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            self.samples.append((time.time_ns(), self._sample()))
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        self._halt.set()
        self.join()

    def _role(self, pid: int) -> str:
        """The stage a process is, from its command line (read every time: a child forked but not yet
        exec'd still shows its parent's)."""
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            return ""
        words = [a.decode(errors="replace") for a in argv]
        if "octolog.tracker.worker" in words:
            return "back end"
        if "octolog" in words and words.index("octolog") + 1 < len(words):
            word = words[words.index("octolog") + 1]
            return {"track": "tracker", "map": "mapper", "log": "session log"}.get(word, word)
        return "other"

    def _sample(self) -> dict[str, float]:
        out: dict[str, float] = {}
        todo = [self.root]
        while todo:
            pid = todo.pop()
            try:
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                for task in os.listdir(f"/proc/{pid}/task"):
                    todo += [int(c) for c in Path(f"/proc/{pid}/task/{task}/children").read_text().split()]
            except OSError:
                continue
            role = self._role(pid) if pid != self.root else "octolog run"
            out[role] = out.get(role, 0.0) + (int(fields[11]) + int(fields[12])) / TICK
        return out

    def between(self, t0_ns: int, t1_ns: int) -> dict[str, float]:
        """CPU seconds each role spent between two wall times (the samples nearest inside)."""
        inside = [s for t, s in self.samples if t0_ns <= t <= t1_ns] or [self.samples[-1][1]]
        first, last = inside[0], inside[-1]
        return {role: last[role] - first.get(role, 0.0) for role in last}


def run_pipeline(source: str, sets: list[str], out: Path, *, live: bool = False) -> dict:
    from octolog.kit.mcaplog import read_wire
    from octolog.schemas import codec, topics

    t0_ns = time.time_ns()
    t0 = time.monotonic()
    paced = ["replay.rate=1", "tracker.live=true"] if live else []
    argv = [sys.executable, "-m", "octolog", "run", "--source", source, "--out", str(out), "--quiet", "--overwrite"]
    for s in [*sets, *paced]:
        argv += ["--set", s]
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL)
    sampler = CpuSampler(proc.pid)
    sampler.start()
    if proc.wait():
        sys.exit(f"bench: {' '.join(argv)} failed")
    sampler.stop()
    wall = time.monotonic() - t0
    end_ns = t0_ns + round(wall * 1e9)
    frame_rx: dict[int, int] = {}
    track_ms, latency_ms, map_ms = [], [], []
    first_frame_ns = last_status_ns = skipped = 0
    frame_topics = (topics.RGBD.name, topics.RGBD_COMPRESSED.name)
    for m in read_wire(out / "session.mcap"):
        if m.topic in frame_topics:
            seq = int.from_bytes(m.data[4:12], "little")  # CDR: 4-byte encapsulation, then uint64 seq
            frame_rx[seq] = m.log_time_ns
            first_frame_ns = first_frame_ns or m.log_time_ns
        elif m.topic == topics.TRACKING_STATUS.name:
            st = codec.decode(m.data, topics.TRACKING_STATUS.msgtype)
            last_status_ns = m.log_time_ns
            if st.state == st.SKIPPED:
                skipped += 1
                continue
            track_ms.append(st.processing_ms)
            if st.seq in frame_rx:
                latency_ms.append((m.log_time_ns - frame_rx[st.seq]) / 1e6)
        elif m.topic == topics.MAP_UPDATE.name:
            map_ms.append(codec.decode(m.data, topics.MAP_UPDATE.msgtype).processing_ms)
    summary = json.loads((out / "summary.json").read_text())
    sizes = {"session.mcap": (out / "session.mcap").stat().st_size,
             "rerun": sum(p.stat().st_size for p in (out / "rerun").glob("*.rrd"))}
    steps = published_steps(out / "session.mcap", out / "groundtruth.txt") if (out / "groundtruth.txt").exists() \
        else {}
    return {"wall": wall, "stream": (last_status_ns - first_frame_ns) * 1e-9,
            "startup": (first_frame_ns - t0_ns) * 1e-9, "end": (end_ns - last_status_ns) * 1e-9,
            "frames": len(frame_rx), "duration": summary["duration_s"],
            "ate_cm": (summary["ate"] or {}).get("rmse_m", float("nan")) * 100, "track_ms": track_ms,
            "latency_ms": latency_ms, "map_ms": map_ms, "keyframes": len(map_ms), "sizes": sizes,
            "skipped": skipped, "steps": steps, "cpu": summary.get("cpu_s", {}),
            "stream_cpu": sampler.between(first_frame_ns, last_status_ns)}


def run_in_process(source: str, sets: list[str]) -> dict:
    """The reference: the same cores in one process, frames decoded as read, no transport, no logging."""
    from octolog.mapper.config import MapperConfig
    from octolog.mapper.core import make_mapper
    from octolog.tracker.config import TrackerConfig, for_source
    from octolog.tracker.factory import make_odometry

    src = open_case(source, sets)
    odom, mapper = make_odometry(for_source(TrackerConfig(), src)), make_mapper(MapperConfig())
    track_ms, map_ms = [], []
    t0 = time.monotonic()
    n = 0
    for f in src.frames():
        t = time.perf_counter()
        res = odom.track(f)
        track_ms.append((time.perf_counter() - t) * 1e3)
        n += 1
        if res.is_keyframe:
            t = time.perf_counter()
            mapper.integrate(res.keyframe_id, res.world_from_camera, f)
            map_ms.append((time.perf_counter() - t) * 1e3)
    stream = time.monotonic() - t0
    moved = odom.finish()
    if moved:
        mapper.correct(moved)
    wall = time.monotonic() - t0
    return {"stream": stream, "wall": wall, "frames": n, "duration": src.duration_ns * 1e-9,
            "track_ms": track_ms, "map_ms": map_ms, "keyframes": len(map_ms)}


def table(runs: list[dict], ref: dict, src_bytes: int) -> list[tuple[str, str, str, str]]:
    def med(key: str) -> float:
        return statistics.median(r[key] for r in runs)

    rtf_stream = statistics.median(r["duration"] / r["stream"] for r in runs)
    rtf_wall = statistics.median(r["duration"] / r["wall"] for r in runs)
    ref_stream, ref_wall = ref["duration"] / ref["stream"], ref["duration"] / ref["wall"]
    track = [x for r in runs for x in r["track_ms"]]
    lat = [x for r in runs for x in r["latency_ms"]]
    mp = [x for r in runs for x in r["map_ms"]]
    mcap_mb = statistics.median(r["sizes"]["session.mcap"] for r in runs) / 1e6
    rrd_mb = statistics.median(r["sizes"]["rerun"] for r in runs) / 1e6
    return [
        ("frames", f"{runs[0]['frames']}", f"{ref['frames']}", ""),
        ("real-time factor, streaming", f"{rtf_stream:.2f}", f"{ref_stream:.2f}", f"{rtf_stream / ref_stream:.2f}x"),
        ("real-time factor, whole run", f"{rtf_wall:.2f}", f"{ref_wall:.2f}", f"{rtf_wall / ref_wall:.2f}x"),
        ("wall s: start-up / streaming / end", f"{med('startup'):.1f} / {med('stream'):.1f} / {med('end'):.1f}",
         f"- / {ref['stream']:.1f} / {ref['wall'] - ref['stream']:.1f}", ""),
        ("tracker ms/frame median / p90", f"{pct(track, 50):.1f} / {pct(track, 90):.1f}",
         f"{pct(ref['track_ms'], 50):.1f} / {pct(ref['track_ms'], 90):.1f}", ""),
        ("frame->pose latency ms median / p90", f"{pct(lat, 50):.1f} / {pct(lat, 90):.1f}", "-", ""),
        ("mapper ms/keyframe median / p90", f"{pct(mp, 50):.1f} / {pct(mp, 90):.1f}",
         f"{pct(ref['map_ms'], 50):.1f} / {pct(ref['map_ms'], 90):.1f}", ""),
        ("keyframes", f"{runs[0]['keyframes']}", f"{ref['keyframes']}", ""),
        ("ATE RMSE, cm", f"{med('ate_cm'):.2f}", "-", ""),
        ("output MB: session.mcap + .rrd", f"{mcap_mb:.0f} + {rrd_mb:.0f}", "-",
         f"{(mcap_mb + rrd_mb) * 1e6 / src_bytes:.2f}x src" if src_bytes else ""),
    ]


BUDGET_ROWS = ("replay", "decode", "features", "tracking", "back end", "tracker: bus, publishing, rest",
               "mapper", "session log", "Rerun (all stages)", "octolog run")


def budget(run: dict) -> dict[str, float]:
    """Milliseconds of CPU per camera frame by stage while frames streamed (BUDGET_ROWS, and "total")."""
    cpu, tracker = run["stream_cpu"], run["cpu"].get("tracker", {})
    buckets = tracker.get("buckets", {})
    rerun = sum(c.get("buckets", {}).get("rerun", 0.0) + c.get("threads", {}).get("rerun", 0.0)
                for c in run["cpu"].values())
    mapper_rerun = sum(run["cpu"].get("mapper", {}).get(k, {}).get("rerun", 0.0) for k in ("buckets", "threads"))
    split = {k: buckets.get(k, 0.0) for k in ("decode", "features", "tracking")}
    tracker_rerun = sum(tracker.get(k, {}).get("rerun", 0.0) for k in ("buckets", "threads"))
    rows = {"replay": cpu.get("replay", 0.0), **split, "back end": cpu.get("back end", 0.0),
            "tracker: bus, publishing, rest": max(0.0, cpu.get("tracker", 0.0) - sum(split.values()) - tracker_rerun),
            "mapper": max(0.0, cpu.get("mapper", 0.0) - mapper_rerun), "session log": cpu.get("session log", 0.0),
            "Rerun (all stages)": rerun, "octolog run": cpu.get("octolog run", 0.0)}
    n = max(1, run["frames"])
    out = {k: v * 1e3 / n for k, v in rows.items()}
    out["total"] = sum(cpu.values()) * 1e3 / n
    return out


def print_rows(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> None:
    w = max(len(r[0]) for r in rows)
    print(f"{header[0]:<{w}}  " + "  ".join(f"{h:>18}" for h in header[1:]))
    for name, *cells in rows:
        print(f"{name:<{w}}  " + "  ".join(f"{c:>18}" for c in cells))


def live_rows(live: list[dict]) -> list[tuple[str, str]]:
    lat = [x for r in live for x in r["latency_ms"]]
    skipped = [r["skipped"] / max(1, r["frames"]) for r in live]
    return [("frames skipped", f"{statistics.median(skipped):.1%}"),
            ("frame->pose latency ms median / p90", f"{pct(lat, 50):.1f} / {pct(lat, 90):.1f}"),
            ("ATE RMSE, cm", f"{statistics.median(r['ate_cm'] for r in live):.2f}"),
            ("keyframes", f"{statistics.median(r['keyframes'] for r in live):.0f}")]


def steps_rows(runs: list[dict]) -> list[tuple[str, str]]:
    s = [r["steps"] for r in runs if r["steps"]]
    if not s:
        return []
    return [("published / LOST frames", f"{statistics.median(x['published'] for x in s):.0f} / "
             f"{statistics.median(x['lost'] for x in s):.0f}"),
            ("published steps > 5 cm off, unflagged", f"{statistics.median(x['bad_steps'] for x in s):.0f}"),
            ("... at an announced map correction or relocalisation", f"{statistics.median(x['flagged_steps'] for x in s):.0f}"),
            ("worst unflagged step error, cm", f"{statistics.median(x['worst_step_m'] for x in s) * 100:.1f}")]


def run_case(name: str, repeat: int, n_live: int, keep: str = "") -> None:
    source, sets = case_source(name)
    with tempfile.TemporaryDirectory() as tmp:
        if keep:  # the session folders stay, to look into (octolog info, octolog eval, Rerun)
            tmp = str(Path(keep) / name)
        runs = [run_pipeline(source, sets, Path(tmp) / f"run{i}") for i in range(repeat)]
        live = [run_pipeline(source, sets, Path(tmp) / f"live{i}", live=True) for i in range(n_live)]
    print(f"\n## {name}: {CASES[name].about}  (load average {os.getloadavg()[0]:.1f} after)")
    if runs:
        print_rows(("lockstep", "pipeline", "in-process", "ratio"), table(runs, run_in_process(source, sets), 0))
    if live:
        print()
        print_rows(("live (paced at 30 fps)", "pipeline"), live_rows(live))
    print()
    cols = ([("lockstep", runs)] if runs else []) + ([("live", live)] if live else [])
    per = {label: [budget(r) for r in rs] for label, rs in cols}
    rows = [(row, *(f"{statistics.median(b[row] for b in per[label]):.1f}" for label, _ in cols))
            for row in (*BUDGET_ROWS, "total")]
    rows.append(("budget (2 cores at 30 fps)", *(f"{BUDGET_MS:.1f}" for _ in cols)))
    print_rows(("CPU ms per camera frame", *(label for label, _ in cols)), rows)
    if cols and cols[0][1][0]["steps"]:
        print()
        print_rows(("published poses", *(label for label, _ in cols)),
                   [tuple([a[0], *(dict(steps_rows(rs))[a[0]] for _, rs in cols)]) for a in steps_rows(cols[0][1])])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="first300,first300x3,turns", help=f"of {', '.join(CASES)}")
    ap.add_argument("--repeat", type=int, default=3, help="lockstep runs per case (medians over runs; 0: live only)")
    ap.add_argument("--live", type=int, default=1, help="runs paced at the camera's rate with the live tracker")
    ap.add_argument("--keep", default="", help="keep each run's session folder under KEEP/CASE/ (default: none kept)")
    args = ap.parse_args()
    print(f"octolog pipeline benchmark: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load average {os.getloadavg()[0]:.1f} before; pipeline = `octolog run` "
          f"with its default outputs (session log, Rerun recordings), {args.repeat} lockstep + {args.live} live "
          f"run(s) per case; in-process = the same cores in one process, no transport, no logging")
    for name in args.cases.split(","):
        run_case(name, args.repeat, args.live, args.keep)


if __name__ == "__main__":
    main()
