"""The one entry point: `octolog <command>`. Commands parse, load config and call a stage's run().

Known errors (OctologError) print one line and exit 1; anything else shows its traceback.
Each command imports its stage inside the function: all stages together (numpy, scipy, OpenCV,
gtsam, open3d, rerun) take seconds to import, `octolog --help` a fraction of one.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import json
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from octolog import __version__
from octolog.kit import cpuclock
from octolog.kit.config import load
from octolog.kit.errors import ConfigError, DiskFull, InputError, OctologError
from octolog.shell import errorfile, record
from octolog.shell.args import add_bus_arguments, add_config_arguments, add_viz_arguments, bus_config, recording_id
from octolog.shell.args import Subcommands, add_log_arguments, command_logging
from octolog.shell.sessiondir import not_a_session
from octolog.shell.statusline import StatusLine, end_latest

if TYPE_CHECKING:
    from octolog.replay.node import ReplayStatus

_status: StatusLine | None = None  # the replay's status line, once it has shown something


def _progress(status: ReplayStatus) -> None:
    """The replay's status line (replay.node.ReplayStatus) on stderr, every 10 frames: redrawn on a
    terminal, else a plain line every few seconds (shell/statusline.py)."""
    global _status
    done, total = status.published, status.total
    if done % 10 and done != total:
        return
    _status = _status or StatusLine()
    _status.show(f"  {status.line()}")
    if done == total:
        _status.end()


def _error_line(text: str) -> None:
    """`text` on a line of its own on stderr: an open progress line is ended first."""
    try:
        end_latest()
        print(text, file=sys.stderr, flush=True)
    except OSError:
        pass  # stderr is a log on a full disk: the error record (errorfile) carries the message


# --- commands ----------------------------------------------------------------------------------
# Each command imports its stage (and shell.run, shell.info, kit.metrics) inside itself: together they
# load Zenoh, numpy, scipy, OpenCV, pyoctomap, gtsam and mcap (seconds), which `octolog --help` and
# every other command should not pay for: with them at the top, `octolog --help` takes 1.1 s instead
# of 0.09 s (2 cores, warm cache; up to 3 s on a loaded machine). The one exception to "first-party
# imports at module top" (docs/architecture.md, "Floors"): each such import says why with `# lazy:`.


def cmd_replay(args: argparse.Namespace) -> int:
    """`octolog replay`: publish a source's frames, or re-run stages of a session (SESSION)."""
    if args.session:
        return cmd_replay_session(args)
    # lazy: the replay stage loads Zenoh, mcap, numpy, scipy and OpenCV
    from octolog.replay import node
    from octolog.replay.config import ReplayConfig

    cfg = load(ReplayConfig, args.config, args.set, section="replay", own=True)
    if args.source:
        cfg = dataclasses.replace(cfg, source=args.source)
    res = node.run(cfg, bus_config(args), rerun=args.rerun, recording_id=recording_id(args),
                   progress=None if args.quiet else _progress)
    print(f"replay: {res.frames} frames in {res.wall_s:.1f} s "
          f"(real-time factor {res.duration_s / res.wall_s if res.wall_s else 0:.2f})")
    return 0


def cmd_replay_session(args: argparse.Namespace) -> int:
    """`octolog replay SESSION`: re-run stages of a recorded session from its log."""
    stages = ("mapper",) if args.from_stage == "tracker" else tuple(args.stages.split(","))
    if args.from_stage not in (None, "tracker"):
        raise ConfigError(f"--from {args.from_stage}: only --from tracker (the mapper rebuilt from the tracker's log)")
    why = not_a_session(Path(args.session))
    if why is not None:
        raise InputError(why)
    out = Path(args.out or (Path(args.session) / "replay"))
    _starting(f"replay: {','.join(stages)} of {args.session}", out)
    from octolog.shell import run  # lazy: the orchestrator loads every stage's config, Zenoh and mcap

    summary = run.replay_session(Path(args.session), out=out, stages=stages, overrides=args.set,
                                 rerun=args.rerun,
                                 recording_id=recording_id(args), quiet=args.quiet, overwrite=args.overwrite)
    print(run.format_summary(summary))
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    """`octolog view`: merge a session's .rrd files and open them in Rerun."""
    from octolog.shell import run  # lazy: the orchestrator loads every stage's config, Zenoh and mcap

    merged = run.merge_rrd(Path(args.session))
    if args.headless or not os.environ.get("DISPLAY"):
        print(f"merged {merged}; open it with: {Path(sys.executable).with_name('rerun')} {merged}")
        return 0
    os.execv(str(Path(sys.executable).with_name("rerun")), ["rerun", str(merged)])


def cmd_track(args: argparse.Namespace) -> int:
    """`octolog track`: the tracker process."""
    # lazy: the tracker stage loads Zenoh, numpy, scipy, OpenCV and gtsam
    from octolog.shell.info import imu_line, prior_line, uninitialised_line
    from octolog.tracker import node
    from octolog.tracker.config import TrackerConfig

    cfg = load(TrackerConfig, args.config, args.set, section="tracker", own=True)
    if args.map:
        cfg = dataclasses.replace(cfg, map=args.map)
    res = node.run(cfg, bus_config(args), trajectory=Path(args.trajectory) if args.trajectory else None,
                   rerun=args.rerun, recording_id=recording_id(args),
                   save_map=Path(args.save_map) if args.save_map else None)
    print(f"tracker: {res.frames} frames, {res.tracked} tracked, {res.lost} lost, {res.skipped} skipped, "
          f"{res.rejected} rejected, {res.keyframes} keyframes, {res.loops} loops closed, "
          f"{res.relocalisations} relocalisations"
          + (f", {res.backend_deferred} keyframes without waiting for the back end" if res.backend_deferred else ""))
    for problem in res.problems[:5]:
        print(f"tracker: rejected {problem}")
    if res.uninitialised is not None:
        print(f"tracker: {uninitialised_line(res.uninitialised)}")
        errorfile.FINDINGS["uninitialised"] = res.uninitialised
    errorfile.FINDINGS["imu"] = res.imu
    print(f"tracker: {imu_line(res.imu)}")
    if res.depth_bias is not None:
        print(f"tracker: {res.depth_bias.summary()}")
        errorfile.FINDINGS["depth_bias"] = res.depth_bias.as_dict()
    if res.prior is not None:
        print(f"tracker: {prior_line(res.prior)}")
        errorfile.FINDINGS["prior_map"] = res.prior
    return 0


def cmd_map(args: argparse.Namespace) -> int:
    """`octolog map`: the mapper process."""
    # lazy: the mapper stage loads Zenoh, mcap, numpy, scipy, numba and pyoctomap
    from octolog.mapper import node
    from octolog.mapper.config import MapperConfig

    cfg = load(MapperConfig, args.config, args.set, section="mapper", own=True)
    res = node.run(cfg, bus_config(args), out_dir=Path(args.out), rerun=args.rerun,
                   recording_id=recording_id(args))
    print(f"mapper: {res.keyframes} keyframes ({res.skipped} skipped), {res.stats.get('occupied_voxels', 0)} occupied "
          f"and {res.stats.get('free_voxels', 0)} free voxels, {res.cloud_points} cloud points → {args.out}")
    for merge in res.merges:
        print(f"mapper: {merge['robot']} placed in the map from a shared place ({merge['inliers']} matches agree)")
    for problem in res.problems[:5]:
        print(f"mapper: {problem}")
    return 0


def cmd_log(args: argparse.Namespace) -> int:
    """`octolog log`: the session logger (every pipeline topic into MCAP)."""
    from octolog.recorder import buslog  # lazy: the session logger loads Zenoh and mcap

    metadata = json.loads(Path(args.metadata).read_text()) if args.metadata else None
    res = buslog.run(bus_config(args), Path(args.out), compression=args.compression, metadata=metadata,
                     stages=tuple(args.stages.split(",")), frames=args.frames)
    errorfile.FINDINGS["statuses"] = dataclasses.asdict(res.statuses)  # for the run's summary (shell/run.py)
    also = f" (+ {', '.join(res.files)})" if res.files else ""
    print(f"log: {sum(res.counts.values())} messages → {res.path}{also}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """`octolog run`: the whole pipeline as processes on this machine."""
    if args.source == "d455":
        record.require_camera()  # no camera: one line, and no session folder left behind
    _starting(f"{args.command}: {args.source}", Path(args.out))
    from octolog.shell import run  # lazy: the orchestrator loads every stage's config, Zenoh and mcap

    summary = run.run_session(
        source=args.source, out=Path(args.out), config=args.config, overrides=args.set, rerun=args.rerun,
        recording_id=recording_id(args), quiet=args.quiet, overwrite=args.overwrite,
        duration_s=getattr(args, "duration", 0.0), router=getattr(args, "router", None),
        ros2_domain=args.ros2_domain, prior_map=getattr(args, "map", None),
    )
    print(run.format_summary(summary))
    return 0


def _starting(what: str, out: Path) -> None:
    """A session's first line, on stdout at once: its imports and stages take seconds to start (more on
    a loaded machine), and a log or terminal should not stay empty meanwhile."""
    print(f"octolog {what} → {out} (stage logs: {out / 'logs'}); starting the stages", flush=True)


def cmd_demo(args: argparse.Namespace) -> int:
    """`octolog demo`: `run` on the synthetic room."""
    args.source = f"synthetic:{args.frames}"
    return cmd_run(args)


def cmd_merge(args: argparse.Namespace) -> int:
    """`octolog merge`: sessions recorded apart into one map."""
    # lazy: the merge loads the mapper (numpy, numba, pyoctomap), Zenoh and mcap
    from octolog.mapper.config import MapperConfig
    from octolog.shell.merge import merge_sessions

    cfg = load(MapperConfig, args.config, args.set, section="mapper", own=True)
    stats = merge_sessions([Path(f) for f in args.sessions], Path(args.out), cfg, overwrite=args.overwrite)
    print(f"merge: {len(args.sessions)} sessions -> {args.out}: {stats['keyframes']} keyframes, "
          f"{stats['occupied_voxels']} occupied voxels, {len(stats['merges'])} placed by a shared place")
    for m in stats["merges"]:
        print(f"  {m['robot']}: its keyframe {m['robot_keyframe']} sees map keyframe {m['map_keyframe']} "
              f"({m['inliers']} of {m['matches']} matches agree)")
    for problem in stats["problems"]:
        print(f"merge: {problem}")
    return 0


def cmd_stitch(args: argparse.Namespace) -> int:
    """`octolog stitch`: a map's shards into the whole map (shell/merge.py)."""
    from octolog.shell.merge import cmd_stitch as stitch  # lazy: loads the mapper (numpy, numba, pyoctomap)

    return stitch(args)


def cmd_import(args: argparse.Namespace) -> int:
    """`octolog import`: a TUM folder or a ROS/RealSense bag into octolog's MCAP layout."""
    from octolog.recorder.importers import import_source, parse_topic_map  # lazy: rosbags, numpy, OpenCV, mcap

    res = import_source(args.source, Path(args.output), overwrite=args.overwrite,
                        topic_map=parse_topic_map(args.map), compression=args.compression,
                        depth_scale_m=args.depth_scale, camera=args.camera)
    print(f"import: {res.kind} {res.source} → {res.output}: {res.total} messages")
    for topic, n in sorted(res.counts.items()):
        print(f"  /{topic.lstrip('/')}: {n}")
    for topic, n in sorted(res.skipped.items()):
        print(f"  skipped {topic}: {n}")
    for note in res.notes:
        print(f"  note: {note}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    """`octolog eval`: ATE and RPE of a trajectory against ground truth."""
    from octolog.kit import metrics  # lazy: numpy

    est, gt = metrics.read_tum(args.trajectory), metrics.read_tum(args.groundtruth)
    a = metrics.ate(est, gt, max_dt_ns=int(args.max_dt * 1e9))
    r = metrics.rpe(est, gt, max_dt_ns=int(args.max_dt * 1e9))
    print(metrics.format_report(a, r))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    """`octolog info`: what an MCAP or OctoMap file holds."""
    from octolog.shell.info import describe  # lazy: numpy, mcap and rosbags

    print(describe(Path(args.file)))
    return 0


def cmd_vocab(args: argparse.Namespace) -> int:
    """`octolog vocab build`: train an ORB vocabulary."""
    from octolog.tracker import vocab  # lazy: numpy and OpenCV

    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ConfigError(f"--out {out}: exists; pass --overwrite to replace it")

    line = StatusLine()

    def progress(done: int, total: int) -> None:
        if not args.quiet and (done % 10 == 0 or done == total):
            line.show(f"  ORB features: {done}/{total} images")
            if done == total:
                line.end()

    res = vocab.build(args.image_dirs, out, k=args.k, levels=args.levels, max_images=args.max_images,
                      n_features=args.features, seed=args.seed, progress=progress)
    print(f"vocab: {res.images} images, {res.descriptors} ORB descriptors → {res.words} words, {res.nodes} nodes "
          f"(k={args.k}, L={args.levels}, seed={args.seed}) → {res.path}")
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    """`octolog router`: host a Zenoh router until Ctrl-C."""
    from octolog.kit.bus import serve_router  # lazy: Zenoh

    listen = tuple(args.listen) or ("tcp/0.0.0.0:7447",)
    serve_router(listen, connect=tuple(args.connect), zenoh_config=args.zenoh_config,
                 ready=lambda: print(f"router: listening on {', '.join(listen)} (Ctrl-C to stop)", flush=True))
    return 0


# --- parser ------------------------------------------------------------------------------------


def _stage_parser(sub: Subcommands, name: str, help_: str) -> argparse.ArgumentParser:
    """A pipeline stage's subcommand: config, transport and viewer flags."""
    p = sub.add_parser(name, help=help_, description=help_)
    add_config_arguments(p)
    add_bus_arguments(p)
    add_viz_arguments(p, session_default=name == "replay")
    return p


def _session_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of a whole-pipeline session (`run`, `demo`)."""
    add_config_arguments(p)
    p.add_argument("--rerun", default="save", metavar="SPEC",
                   help="save (default: one .rrd per stage in OUT/rerun), off, save:DIR or connect[:URL]")
    p.add_argument("--recording-id", default=None, help="Rerun recording id (default: a new one)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a session already in --out (its files are removed first)")
    p.add_argument("--ros2-domain", type=int, default=-1, metavar="ID",
                   help="the stages also publish standard-typed topics as ROS 2's rmw_zenoh does (default off)")


def _add_session_commands(sub: Subcommands) -> None:
    """`run` and `demo`: the whole pipeline on one machine."""
    p = sub.add_parser("run", help="whole pipeline as separate processes on one machine")
    p.add_argument("--source", required=True,
                   help="tum:PATH, mcap:PATH, synthetic[:N][:KEY=VALUE...], or live: d455 (a camera) or d455:software (simulated)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--duration", type=float, default=0.0,
                   help="live sources: stop after this many seconds of camera time (0: until the stream ends)")
    p.add_argument("--router", metavar="ENDPOINT",
                   help="the stages join this Zenoh router (e.g. tcp/127.0.0.1:7447) instead of one hosted on a "
                        "free loopback port: to watch or probe the session's topics from another process")
    p.add_argument("--map", metavar="SESSION_OR_MAP",
                   help="track in the SLAM map an earlier session saved (its folder, or its slam_map.npz): "
                        "tracker.map; tracker.mode=localize only tracks in it")
    _session_arguments(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", help="the pipeline on the built-in synthetic room")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--frames", type=int, default=150, help="synthetic frames (default 150, 5 s)")
    _session_arguments(p)
    p.set_defaults(func=cmd_demo)


def _add_stage_commands(sub: Subcommands) -> None:
    """`replay`, `track`, `map`, `log`: one stage each, on any machine of a bus."""
    p = _stage_parser(sub, "replay", "publish a source's frames on the bus, or re-run stages of a recorded SESSION")
    p.add_argument("session", nargs="?", help="a session folder (made by octolog run): re-run stages from its log")
    p.add_argument("--source", help="tum:PATH, mcap:PATH or synthetic[:N][:KEY=VALUE...]")
    p.add_argument("--stages", default="tracker,mapper", help="SESSION: stages to run fresh (tracker,mapper or mapper)")
    p.add_argument("--from", dest="from_stage", metavar="STAGE",
                   help="SESSION: feed the logged output of STAGE (tracker) to fresh downstream stages")
    p.add_argument("--out", help="SESSION: output folder (default SESSION/replay)")
    p.add_argument("--overwrite", action="store_true", help="SESSION: replace a session already in --out")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_replay)

    p = _stage_parser(sub, "track", "run the tracker on frames from the bus")
    p.add_argument("--trajectory", help="write the TUM-format trajectory here at the end")
    p.add_argument("--map", help="track in a saved SLAM map: a session folder or its slam_map.npz (tracker.map)")
    p.add_argument("--save-map", help="write the SLAM map here at the end (the format: docs/formats.md)")
    p.set_defaults(func=cmd_track)

    p = _stage_parser(sub, "map", "run the mapper on keyframes from the bus")
    p.add_argument("--out", default=".", help="folder for map.bt, cloud.ply, map_stats.json")
    p.set_defaults(func=cmd_map)

    p = sub.add_parser("log", help="record every pipeline topic on the bus into an MCAP file")
    add_bus_arguments(p)
    p.add_argument("--out", required=True,
                   help="an MCAP file (.mcap), or a session folder: session.mcap, config.toml from the stages' "
                        "configs on the bus, trajectory.txt; `octolog replay FOLDER --from tracker` re-runs its mapper")
    p.add_argument("--frames", action=argparse.BooleanOptionalAction, default=True,
                   help="log the camera frames (default); --no-frames on a machine across a link from the camera "
                        "keeps them on the camera's side")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="lz4",
                   help="chunk compression (default lz4: the fastest to write)")
    p.add_argument("--metadata", metavar="JSON", help="file of {name: {key: value}} metadata records")
    p.add_argument("--stages", default="replay,tracker,mapper", help="producers whose end messages end the log")
    p.set_defaults(func=cmd_log)


def _add_file_commands(sub: Subcommands) -> None:
    """`import`, `eval`, `view`, `info`: work on files."""
    p = sub.add_parser("import", help="a TUM folder, RealSense .bag/.db3 or ROS bag → octolog MCAP")
    p.add_argument("source", help="TUM folder, .bag (ROS 1), .db3 or rosbag2 folder (ROS 2), .mcap")
    p.add_argument("output", help="the MCAP file to write")
    p.add_argument("--map", action="append", default=[], metavar="SRC=DST", help="topic mapping (repeatable)")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="zstd")
    p.add_argument("--depth-scale", type=float, default=None, help="metres per depth unit, if the source lacks it")
    p.add_argument("--camera", default="", metavar="NAME",
                   help="a TUM folder's camera (freiburg1/2/3) when its name does not say it")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=cmd_import)

    p = sub.add_parser("eval", help="ATE and RPE of a TUM trajectory against ground truth")
    p.add_argument("trajectory")
    p.add_argument("groundtruth")
    p.add_argument("--max-dt", type=_positive_seconds, default=0.02, help="association window in seconds (default 0.02)")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("view", help="merge a session's .rrd files into one recording and open it in Rerun")
    p.add_argument("session")
    p.add_argument("--headless", action="store_true", help="only write SESSION/rerun/session.rrd")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("info", help="what a session folder, an MCAP file or an OctoMap file (.bt, .ot) holds")
    p.add_argument("file", help="a session folder, an MCAP recording or session log, or a .bt/.ot map")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("merge", help="sessions recorded apart into one map, placed by the places they share")
    p.add_argument("sessions", nargs="+", help="session folders (octolog run --out); the first one's world is the map's")
    p.add_argument("--out", required=True, help="folder for the merged map.bt, cloud.ply, map_stats.json")
    p.add_argument("--overwrite", action="store_true", help="replace a merged map already in --out")
    p.add_argument("--config", help="TOML file with a [mapper] section")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="mapper config override")
    p.set_defaults(func=cmd_merge)
    p = sub.add_parser("stitch", help="a map's shards (octolog map --set shard=K/N) into the whole map")
    p.add_argument("shards", nargs="+", help="the shards' --out folders (each with shard.npz)")
    p.add_argument("--out", required=True, help="folder for the stitched map.bt, cloud.ply, grid, map_stats.json")
    p.add_argument("--overwrite", action="store_true", help="replace a map already in --out")
    p.set_defaults(func=cmd_stitch)


def _add_vocab_command(sub: Subcommands) -> None:
    """`vocab build`: ORB vocabularies for the ORB-SLAM3 backend."""
    p = sub.add_parser("vocab", help="ORB vocabularies for the ORB-SLAM3 tracker backend")
    vsub = p.add_subparsers(dest="vocab_command", required=True)
    v = vsub.add_parser("build", help="train a DBoW2 text vocabulary (ORBvoc.txt format) from images",
                        description="Train a DBoW2 text vocabulary (the ORBvoc.txt format ORB-SLAM3 loads) on ORB "
                                    "features of the images in IMAGE_DIR...: hierarchical k-majority clustering, "
                                    "IDF word weights. Same images and seed: byte-identical file.")
    v.add_argument("image_dirs", nargs="+", metavar="IMAGE_DIR", help="folders of .png/.jpg images")
    v.add_argument("--out", required=True, metavar="FILE", help="vocabulary text file to write")
    v.add_argument("--k", type=int, default=10, help="branching factor, 2..20 (default 10)")
    v.add_argument("--levels", type=int, default=6, help="tree depth, 1..10 (default 6)")
    v.add_argument("--max-images", type=int, default=None, metavar="N", help="use N evenly spaced images")
    v.add_argument("--features", type=int, default=1000, metavar="N", help="ORB features per image (default 1000)")
    v.add_argument("--seed", type=int, default=0, help="k-means++ seed (default 0)")
    v.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    v.add_argument("--quiet", action="store_true", help="no progress line")
    v.set_defaults(func=cmd_vocab)


def _add_router_command(sub: Subcommands) -> None:
    """`router`: a Zenoh router hosted in Python."""
    p = sub.add_parser("router", help="host a Zenoh router (no zenohd needed)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="where stages and robots connect (default tcp/0.0.0.0:7447; repeat for several)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="another router to join (a robot's own router joining the server's)")
    p.add_argument("--zenoh-config", metavar="FILE")
    p.set_defaults(func=cmd_router)


def build_parser() -> argparse.ArgumentParser:
    """The `octolog` parser with every subcommand (in the order `octolog --help` lists them)."""
    parser = argparse.ArgumentParser(prog="octolog", description="RGB-D record/replay and mapping over Zenoh.")
    parser.add_argument("--version", action="version", version=f"octolog {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_session_commands(sub)
    _add_stage_commands(sub)
    record.add_parsers(sub)
    _add_file_commands(sub)
    _add_vocab_command(sub)
    _add_router_command(sub)
    add_log_arguments(parser)
    return parser


_stopping = False  # a first Ctrl-C or SIGTERM is being handled


def _positive_seconds(text: str) -> float:
    """An argparse type: a time window in seconds, > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text}: want a window of more than 0 seconds")
    return value


def _terminate(signum: int, frame: object) -> None:
    """Ctrl-C or SIGTERM: unwind (context managers finish files and stop child processes); another
    while that runs is said and ignored, so the stop finishes what was recorded instead of ending in
    a traceback part-way (every stop is bounded)."""
    global _stopping
    if _stopping:
        with contextlib.suppress(OSError):
            print("octolog: stopping already; finishing what was written", file=sys.stderr, flush=True)
        return
    _stopping = True
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Entry point: run a command; a known error prints one line and returns 1."""
    args = build_parser().parse_args(argv)
    if getattr(args, "rerun", "") is None:
        args.rerun = "save" if getattr(args, "session", None) else "off"
    signal.signal(signal.SIGTERM, _terminate)
    signal.signal(signal.SIGINT, _terminate)
    errorfile.stop_with_parent()
    try:
        with command_logging(args):
            return _run_command(args)
    finally:
        if "octolog.kit.bus.screening" in sys.modules:  # a command that took samples off a bus
            from octolog.kit.bus import screening  # lazy: only a command that used a bus has it (Zenoh) loaded

            if "octolog.kit.viz" in sys.modules:
                from octolog.kit import viz  # lazy: loaded already (a stage that logs to Rerun)

                if viz.VIEWER_MISSED:
                    errorfile.FINDINGS["viewer_missed"] = dict(viz.VIEWER_MISSED)
            errorfile.write_report(screening.totals(), cpuclock.report())


def _run_command(args: argparse.Namespace) -> int:
    """Run the command; a known error prints one line and returns 1."""
    try:
        return int(args.func(args))
    except OctologError as exc:
        errorfile.write(exc)  # for `octolog run`, when this is one of its stages; first: stderr may be full
        _error_line(f"octolog {args.command}: error: {exc}")
        return 1
    except BrokenPipeError:  # the reader went away (`octolog info ... | head`): stop quietly
        # stdout to /dev/null: Python's own flush at exit would hit the closed pipe again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
        # a write no stage guards (a trajectory, a log line): still a known error, named by its file
        full = DiskFull(f"disk full: {exc.filename or 'a write'} failed: {exc.strerror}")
        errorfile.write(full)
        _error_line(f"octolog {args.command}: error: {full}")
        return 1
    except KeyboardInterrupt:
        _error_line(f"octolog {args.command}: interrupted")
        return 130
    except Exception as exc:
        # a stop (Ctrl-C, SIGTERM) that a library turned into its own error: open3d's import raises
        # ImportError("initialization failed") when interrupted part-way
        if not _caused_by_interrupt(exc):
            raise
        _error_line(f"octolog {args.command}: interrupted")
        return 130


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is among `exc`'s causes."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


if __name__ == "__main__":
    sys.exit(main())
