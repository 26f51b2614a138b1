"""Flags shared by the commands: transport, Rerun, config, log level (as zenoh-python's and rerun's helpers)."""

from __future__ import annotations

import argparse
import uuid
from contextlib import AbstractContextManager
from logging import Handler
from typing import TypeAlias

from octolog.kit import logs
from octolog.kit.busconfig import BusConfig

# what `ArgumentParser.add_subparsers` returns, which the commands are added to (argparse's own name for it
# is private, and generic only in typeshed: hence the string)
Subcommands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def add_bus_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("transport (Zenoh)")
    g.add_argument("--mode", choices=("peer", "client", "router"), default="peer", help="Zenoh mode (default peer)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/10.0.0.2:7447")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447")
    g.add_argument("--namespace", default="", help="key prefix for every topic (e.g. robot1)")
    g.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config (TLS, access control, ...)")
    g.add_argument("--no-multicast", action="store_true", help="disable multicast scouting")
    g.add_argument("--max-held-mb", type=int, default=BusConfig.max_held_mb, metavar="MB",
                   help="samples held behind a gap in a publisher's stream, at most (default %(default)s)")
    g.add_argument("--ros2-domain", type=int, default=-1, metavar="ID",
                   help="also publish standard-typed topics as ROS 2's rmw_zenoh does, in this domain (default off)")


def bus_config(args: argparse.Namespace) -> BusConfig:
    cfg = BusConfig(mode=args.mode, connect=tuple(args.connect), listen=tuple(args.listen),
                    namespace=args.namespace, zenoh_config=args.zenoh_config,
                    multicast_scouting=not args.no_multicast, max_held_mb=args.max_held_mb,
                    ros2_domain=args.ros2_domain)
    cfg.validate()
    return cfg


def add_viz_arguments(p: argparse.ArgumentParser, *, session_default: bool = False) -> None:
    """`--rerun`, `--recording-id`; `session_default`: the command also re-runs a SESSION, whose
    recordings are saved into OUT/rerun unless told otherwise (`replay`)."""
    g = p.add_argument_group("Rerun")
    default = "off (default; re-running a SESSION: save into OUT/rerun)" if session_default else "off (default)"
    g.add_argument("--rerun", default=None, metavar="SPEC",
                   help=f"{default}, save:DIR (DIR/STAGE.rrd) or connect[:URL] (a viewer; one not there is a warning)")
    g.add_argument("--recording-id", default=None, help="shared by all stages of one session")


def add_config_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE",
                   help="TOML file with [replay] [tracker] [mapper] [recorder] sections (each command reads its own)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key (KEY or SECTION.KEY; `run`: SECTION.KEY)")


def recording_id(args: argparse.Namespace) -> str:
    return args.recording_id or str(uuid.uuid4())


# a stage's command -> the stage it runs, as its log lines and `octolog run`'s logs/STAGE.log name it
STAGE_OF_COMMAND = {"track": "tracker", "map": "mapper", "record": "recorder"}


def add_log_arguments(parser: argparse.ArgumentParser) -> None:
    """`--log-level` on every command of `parser` (each subcommand that takes no further subcommand)."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    for sub in (p for a in subs for p in a.choices.values()):
        add_log_arguments(sub)
    if not subs:
        parser.add_argument("--log-level", choices=logs.LEVELS, default=logs.DEFAULT_LEVEL,
                            help="the least severe log lines shown, on stderr (default %(default)s)")


def command_logging(args: argparse.Namespace) -> AbstractContextManager[Handler]:
    """The process's logging for the command in `args`: its stage's name, at `--log-level`."""
    return logs.configured(STAGE_OF_COMMAND.get(args.command, args.command),
                           getattr(args, "log_level", logs.DEFAULT_LEVEL))
