"""`octolog record` and `octolog recover`: parsers and thin command functions.

`add_parsers` registers both on octolog's subcommand parser (`octolog.shell.cli`).
"""

from __future__ import annotations

import argparse
import json
import re
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from octolog.kit.config import load, to_dict, to_toml
from octolog.kit.errors import ConfigError
from octolog.shell.args import Subcommands, add_bus_arguments, add_config_arguments, add_viz_arguments, bus_config
from octolog.shell.statusline import StatusLine
from octolog.shell.versions import versions

if TYPE_CHECKING:  # for annotations only: the commands import the recorder themselves (see below)
    from octolog.recorder.config import RecorderConfig
    from octolog.recorder.recording_types import RecorderStatus, RecordResult

# The recorder's modules are imported inside the commands below (`# lazy:`), never here: they load
# pyrealsense2, OpenCV, mcap and Zenoh (0.3 s), and cli.py imports this module for every command's
# parser. With shell/cli.py, the documented exception to "first-party imports at module top".

_PROFILE = re.compile(r"^(\d+)x(\d+)@(\d+)$")


def add_parsers(sub: Subcommands) -> None:
    """Register `record` and `recover` on an argparse subparsers object."""
    p = sub.add_parser("record", help="record a RealSense camera (colour, depth, IMU) to MCAP",
                       description="Record colour, depth and IMU to MCAP (ROS 2 profile) with calibration, "
                                   "optionally publishing live on Zenoh. Ctrl-C or SIGTERM finish the file.")
    p.add_argument("out", help="MCAP file to write (with splitting: OUT_0000.mcap, OUT_0001.mcap, ...), or a "
                               "session folder (no .mcap suffix): OUT/session.mcap, config.toml, summary.json")
    p.add_argument("--duration", type=float, default=0.0, metavar="S", help="stop after S seconds of sensor time")
    p.add_argument("--overwrite", action="store_true", help="replace an existing recording")
    p.add_argument("--publish", action="store_true", help="also publish the topics and camera/rgbd live on Zenoh")
    p.add_argument("--quiet", action="store_true", help="no status line")
    g = p.add_argument_group("camera")
    g.add_argument("--backend", choices=("realsense", "software"),
                   help="realsense (default) or software: a simulated D455 (no camera needed)")
    g.add_argument("--paced", action="store_true",
                   help="software: push frames at the profile's rate in wall time, like a camera (default: on demand)")
    g.add_argument("--serial", help="camera serial number, when several are attached")
    g.add_argument("--color", metavar="WxH@FPS", help="colour profile (default 1280x720@30)")
    g.add_argument("--depth", metavar="WxH@FPS", help="depth profile (default 848x480@30)")
    g.add_argument("--depth-streams", choices=("aligned", "raw", "both"),
                   help="depth aligned to colour (default), as measured (raw), or both")
    g.add_argument("--gyro", type=int, metavar="HZ", help="gyro rate (D455: 200 or 400; default: device default)")
    g.add_argument("--accel", type=int, metavar="HZ", help="accel rate (D455: 63/250 or 100/200 by IMU chip)")
    g.add_argument("--no-imu", action="store_true", help="do not record the IMU")
    g.add_argument("--depth-units", type=float, metavar="M", help="metres per depth unit (D455 default 0.001)")
    g.add_argument("--preset", metavar="NAME", help="visual preset: default, hand, high_accuracy, high_density, ...")
    g.add_argument("--emitter", choices=("on", "off", "auto"), help="IR projector")
    g.add_argument("--auto-exposure", choices=("on", "off"), help="auto exposure of colour and depth sensors")
    g = p.add_argument_group("file")
    g.add_argument("--color-codec", choices=("raw", "jpeg"), help="colour as raw rgb8 or JPEG (default jpeg)")
    g.add_argument("--depth-codec", choices=("raw", "png"),
                   help="depth as raw 16UC1 (default) or lossless 16-bit PNG (~30%% smaller, ~40%% more CPU)")
    g.add_argument("--compression", choices=("none", "lz4", "zstd"), help="MCAP chunk compression (default lz4)")
    g.add_argument("--split-size", type=float, metavar="MB", help="start a new file every MB megabytes")
    g.add_argument("--split-duration", type=float, metavar="S", help="start a new file every S seconds")
    add_config_arguments(p)
    add_bus_arguments(p)
    add_viz_arguments(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("recover", help="rebuild a complete MCAP file from one a killed recorder left",
                       description="Copy every intact chunk of IN into a complete, indexed OUT "
                                   "(a killed recorder loses at most its last, unfinished chunk).")
    p.add_argument("input", help="damaged or unfinished MCAP file")
    p.add_argument("output", help="new MCAP file")
    p.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), help="default: as in INPUT")
    p.set_defaults(func=cmd_recover)


def overrides(args: argparse.Namespace) -> list[str]:
    """Command-line flags as config overrides (they win over --config and --set)."""
    out = list(getattr(args, "set", None) or [])
    for flag, key in (("color", "color"), ("depth", "depth")):
        value = getattr(args, flag)
        if value:
            m = _PROFILE.match(value)
            if not m:
                raise ConfigError(f"--{flag} {value!r}: want WIDTHxHEIGHT@FPS, e.g. 1280x720@30")
            out += [f"{key}.width={m[1]}", f"{key}.height={m[2]}", f"{key}.fps={m[3]}"]
    simple = {"backend": "backend", "serial": "serial", "gyro": "gyro_fps", "accel": "accel_fps",
              "depth_units": "depth_units_m", "preset": "visual_preset", "emitter": "emitter",
              "color_codec": "color_codec", "depth_codec": "depth_codec", "compression": "compression",
              "split_size": "split_size_mb", "split_duration": "split_duration_s"}
    for flag, key in simple.items():
        value = getattr(args, flag)
        if value is not None:
            out.append(f'{key}="{value}"' if isinstance(value, str) else f"{key}={value}")
    if args.no_imu:
        out.append("imu=false")
    if args.paced:
        out.append("software.paced=true")
    if args.depth_streams:
        out += [f"aligned_depth={str(args.depth_streams in ('aligned', 'both')).lower()}",
                f"raw_depth={str(args.depth_streams in ('raw', 'both')).lower()}"]
    if args.auto_exposure:
        out += [f'color_auto_exposure="{args.auto_exposure}"', f'depth_auto_exposure="{args.auto_exposure}"']
    return out


def _status_printer(line: StatusLine) -> Callable[[RecorderStatus], None]:
    """The recorder's status on `line`: redrawn on a terminal, else a plain line every few seconds."""
    from octolog.recorder.recording_types import format_status  # lazy: numpy, rosbags

    def show(status: RecorderStatus) -> None:
        line.show(format_status(status))

    return show


def cmd_record(args: argparse.Namespace) -> int:
    """`octolog record`: capture from the camera into an MCAP file or a session folder."""
    # lazy: the recorder stage loads pyrealsense2, Zenoh, mcap, numpy and OpenCV
    from octolog.recorder import node
    from octolog.recorder.config import RecorderConfig

    cfg = load(RecorderConfig, args.config, overrides(args), section="recorder", own=True)
    if args.duration < 0:
        raise ConfigError(f"--duration {args.duration}: want >= 0 seconds")
    out = Path(args.out)
    folder = out.suffix != ".mcap"
    if folder:  # a session folder, like `octolog run` makes
        out.mkdir(parents=True, exist_ok=True)
        out = out / "session.mcap"
    backend = None
    if cfg.backend == "software" and cfg.software.scene == "room":
        # lazy: replay's renderer (open3d and the room's textures on a cold cache)
        from octolog.shell import simcamera

        backend = simcamera.backend(cfg, args.duration, quiet=args.quiet)  # every frame rendered before it starts
    line = StatusLine()
    res = node.run(cfg, out, bus_cfg=bus_config(args) if args.publish else None,
                   rerun=getattr(args, "rerun", None) or "off",
                   recording_id=getattr(args, "recording_id", None) or str(uuid.uuid4()),
                   duration_s=args.duration, overwrite=args.overwrite,
                   status=None if args.quiet else _status_printer(line), backend=backend)
    line.end()
    frames = ", ".join(f"{s} {st.frames}" for s, st in res.streams.items() if st.frames)
    drops = ", ".join(f"{s} {st.dropped}" for s, st in res.streams.items() if st.dropped) or "none"
    live = sum(st.live_drops for st in res.streams.values())
    span = (res.last_stamp_ns - res.first_stamp_ns) / 1e9
    if folder:
        _write_session_files(out.parent, cfg, res)
    print(f"record: {res.messages} messages ({frames}) over {span:.1f} s, {res.bytes / 1e6:.1f} MB "
          f"-> {', '.join(map(str, res.paths))}; dropped: {drops}"
          + (f"; live publishing skipped {live}" if live else "")
          + (f"; held back {res.held_back} (the tracker had recorder.publish_window frames)" if res.held_back else "")
          + f"; stopped: {res.stop_reason}")
    return 0


def _write_session_files(folder: Path, cfg: RecorderConfig, res: RecordResult) -> None:
    """config.toml and summary.json beside a recording, as in a session folder from `octolog run`."""
    (folder / "config.toml").write_text(to_toml({"recorder": to_dict(cfg)}))
    streams = {name: {"frames": st.frames, "dropped": st.dropped} for name, st in res.streams.items()}
    (folder / "summary.json").write_text(json.dumps(
        {"source": f"record:{cfg.backend}", "streams": streams, "dropped": res.dropped,
         "stop_reason": res.stop_reason, "span_s": (res.last_stamp_ns - res.first_stamp_ns) / 1e9,
         "files": sorted(p.name for p in res.paths) + ["config.toml", "summary.json"],
         "wall_s": round(res.wall_s, 3), "versions": versions()}, indent=2, sort_keys=True) + "\n")


def require_camera() -> None:
    """A one-line error unless a RealSense camera is attached (`run --source d455`, before any file)."""
    from octolog.recorder.realsense_camera import check_attached  # lazy: pyrealsense2

    check_attached()


def cmd_recover(args: argparse.Namespace) -> int:
    """`octolog recover`: rebuild a complete MCAP file from one a killed recorder left."""
    from octolog.recorder.recover import recover  # lazy: mcap, numpy, rosbags

    r = recover(Path(args.input), Path(args.output), overwrite=args.overwrite, compression=args.compression)
    state = "was complete" if r.source_complete else f"was cut short ({r.problem}); {r.bytes_lost} bytes lost"
    print(f"recover: {r.messages} messages from {r.chunks} chunks -> {r.out} (source {state})")
    return 0
