"""`octolog run` / `octolog demo`: the whole pipeline as separate OS processes on one machine.

The orchestrator hosts a Zenoh router on a free loopback port, starts the session logger, mapper,
tracker and replay as child processes (peers that connect to the router, multicast off, so two runs
never cross-talk), watches them, and evaluates the result. If any child dies, the others notice it
through liveliness and stop; this process names the culprit and exits 1. A mapper killed by a
signal (not asked to stop) is started again and rebuilds the same map from the tracker's history.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from octolog import __version__
from octolog.kit import metrics
from octolog.kit.calibration import imu_keys
from octolog.kit.config import load, to_dict, to_toml
from octolog.kit.errors import ConfigError, InputError, OctologError, StageError
from octolog.kit.imu import ImuNoise
from octolog.kit.mcaplog import message_counts, read_wire, summarize, time_span
from octolog.kit.viz import COPY_ENV, DEFAULT_VIEWER, parse_spec, viewer_unreachable
from octolog.mapper.config import MapperConfig
from octolog.recorder.buslog import StatusTally
from octolog.recorder.config import RecorderConfig
from octolog.replay import source_gravity
from octolog.replay.config import ReplayConfig
from octolog.replay.imu import has_imu
from octolog.replay.sources import Source, backend_deferred, open_source
from octolog.schemas import codec
from octolog.schemas import topics as T
from octolog.schemas.topics import RGBD, RGBD_COMPRESSED, TRACKING_STATUS
from octolog.schemas.wirecompression import SOURCE
from octolog.shell import errorfile, simcamera
from octolog.shell.children import HostedRouter, StageProcesses, router_unreachable
from octolog.shell.finishing import Finishing
from octolog.shell.info import depth_bias_line, imu_line, movers_line, prior_line, uninitialised_line
from octolog.shell.priormap import check_prior, prior_mapper
from octolog.shell.sessiondir import INCOMPLETE, incomplete_reason, not_a_session, prepare_out
from octolog.shell.versions import versions
from octolog.tracker.config import TrackerConfig, for_source
from octolog.tracker.mapfile import FILENAME as MAP_FILENAME
from octolog.tracker.mapfile import map_path

log = logging.getLogger(__name__)

STAGES = ("log", "mapper", "tracker", "replay")


NOT_ALIGNED = "not gravity-aligned: no accelerometer, the first camera is assumed level (set mapper.grid_up)"


@dataclass
class SessionSummary:
    """What `octolog run` reports: frames, times, ATE, map statistics and the files written."""

    out: Path
    source: str
    frames: int = 0
    wall_s: float = 0.0
    duration_s: float = 0.0
    tracker: dict = field(default_factory=dict)
    map: dict = field(default_factory=dict)
    ate: dict | None = None
    ate_note: str = ""  # why there is no ATE although there is a ground truth (too few poses to align)
    files: dict[str, str] = field(default_factory=dict)
    malformed: dict[str, dict[str, int]] = field(default_factory=dict)  # stage -> topic -> samples dropped
    map_frame: str = NOT_ALIGNED  # whether the map frame's z is up, and where that came from
    depth_bias: dict | None = None  # the tracker's estimate of the depth camera's systematic error (summary.json)
    imu: dict | None = None  # what the tracker's IMU did (summary.json; None: no IMU, or vision only)
    prior_map: dict | None = None  # what became of the saved map the tracker was given (tracker.map)
    uninitialised: dict | None = None  # the tracker never made a first keyframe: why (tracker.report.json)
    movers: dict | None = None  # what the mapper kept out as moving (map_stats.json `movers`)
    viewer_missed: dict | None = None  # `--rerun connect`: the viewer no stage could reach (kit/viz.py)
    frame_counts: dict = field(default_factory=dict)  # summary.json `frames`: published, consumed, skipped, ...


# Live sources: a D455 (pyrealsense2) or the simulated one (its software device, paced at the
# profile's rate). The recorder stands where the replay stands: it records the camera in full
# (OUT/recording.mcap) and publishes camera/rgbd; the tracker runs live (it skips frames when behind).
LIVE_SOURCES = {"d455": "realsense", "d455:software": "software"}


@dataclass
class LiveSource:
    """What the orchestrator knows of a live camera before it runs: no frames; a ground truth only
    for the simulated one (shell/simcamera.py: its path, rendered ahead)."""

    name: str
    readout_s: float = 0.0  # the D455's colour camera has a global shutter
    duration_ns: int = 0  # known from the session log afterwards
    groundtruth: str = ""  # TUM text

    def groundtruth_tum(self) -> str | None:
        return self.groundtruth or None

    def gravity_up(self) -> None:
        return None  # the live D455's accelerometer is not read for gravity yet


def _map_frame(cfg: MapperConfig, src: Source | LiveSource, *, imu: bool) -> tuple[MapperConfig, dict[str, str] | None]:
    """The mapper's config with `grid_up` from the source's accelerometer when the user left it
    unset (octolog.replay.source_gravity), and what to record of it in the session's metadata; `imu`: the
    tracker fuses an IMU, whose estimate the mapper takes later (the file's up is served on
    camera/gravity meanwhile, mapper/mapframe.py)."""
    if cfg.grid_up:
        return cfg, {"note": "up given by mapper.grid_up"}
    if isinstance(src, LiveSource) or imu:  # the mapper reads the live camera's accelerometer (mapper/mapframe.py)
        return cfg, None
    found = source_gravity.source_up(src)
    if found is None:
        return cfg, None
    up_t, note = tuple(float(v) for v in found[0]), found[1]
    return dataclasses.replace(cfg, grid_up=up_t), {"up": json.dumps(up_t), "note": note}


def _split_overrides(overrides: list[str], *, live: bool = False) -> dict[str, list[str]]:
    """`tracker.n_features=800` goes to the tracker as `n_features=800`."""
    per: dict[str, list[str]] = {"replay": [], "tracker": [], "mapper": [], **({"recorder": []} if live else {})}
    for item in overrides:
        section, dot, rest = item.partition(".")
        if not dot or section not in per:
            raise ConfigError(f"--set {item!r}: want {', '.join(f'{k}.KEY=V' for k in per)}")
        per[section].append(rest)
    return per


def _resolve_configs(source: str, config: str | None, per: dict[str, list[str]]) -> dict[str, Any]:
    """Each stage's config from the file and the overrides; the replay's source and consumers set here."""
    replay = load(ReplayConfig, config, per["replay"], section="replay")
    consumers = ("tracker", "mapper", "log") if replay.play == "camera" else ("mapper", "log")
    replay = dataclasses.replace(replay, source=source, wait_for=consumers)
    cfgs = {
        "replay": replay,
        "tracker": load(TrackerConfig, config, per["tracker"], section="tracker"),
        "mapper": load(MapperConfig, config, per["mapper"], section="mapper"),
    }
    if source in LIVE_SOURCES:
        rec = _live_resolution(load(RecorderConfig, config, per["recorder"], section="recorder"), config,
                               per["recorder"])
        backend = LIVE_SOURCES[source]
        software = dataclasses.replace(rec.software, paced=True) if backend == "software" else rec.software
        # capture starts once the tracker and the session log listen: neither misses a frame. The
        # mapper joins when it is up (its start costs more CPU than the tracker's, and it is niced):
        # the keyframes it missed come from the tracker's history (kit/bus, `keep_mb`)
        cfgs["recorder"] = dataclasses.replace(rec, backend=backend, software=software, wait_for=LIVE_CONSUMERS)
    return cfgs


LIVE_CONSUMERS = ("tracker", "log")  # the stages a live camera waits for before it captures

# A live session's camera, unless the config file or --set says otherwise: what the tracker and mapper
# are measured at. At the recorder's own default (1280x720 colour, 848x480 depth, for recording alone)
# two cores fell behind at 30 fps: the simulated camera held back 4-18 % of its frames, at 640x480
# under 1 % (docs/results.md, "Pipeline and live").
LIVE_COLOUR = LIVE_DEPTH = (640, 480)


def _live_resolution(rec: RecorderConfig, config: str | None, sets: list[str]) -> RecorderConfig:
    """The recorder config with LIVE_COLOUR / LIVE_DEPTH for a stream whose size nobody set."""
    given = {s.split("=", 1)[0].split(".")[0] for s in sets}
    if config:
        import tomllib

        try:
            given |= set(tomllib.loads(Path(config).read_text()).get("recorder", {}))
        except (OSError, tomllib.TOMLDecodeError):
            pass  # load() above has named the problem already
    sizes = {}
    for stream, (w, h) in (("color", LIVE_COLOUR), ("depth", LIVE_DEPTH)):
        if stream not in given:
            sizes[stream] = dataclasses.replace(getattr(rec, stream), width=w, height=h)
    return dataclasses.replace(rec, **sizes)


def run_session(*, source: str, out: Path, config: str | None = None, overrides: list[str] | None = None,
                rerun: str = "save", recording_id: str, quiet: bool = False,
                overwrite: bool = False, duration_s: float = 0.0, router: str | None = None,
                ros2_domain: int = -1, prior_map: str | None = None) -> SessionSummary:
    """Run the whole pipeline on `source` into `out` (config, logs, session.mcap, map, trajectory).

    Until it succeeds, `out` holds an INCOMPLETE file; a failed run writes its error there.
    """
    live = source in LIVE_SOURCES
    # a live camera: the tracker keeps up by skipping frames (each skip on record), and the camera
    # publishes no frame while the tracker has two in hand and lags (it would skip it), unless told otherwise
    live_sets = ["tracker.live=true", "recorder.publish_window=2"] if live else []
    # the camera does not wait for the mapper (LIVE_CONSUMERS): the tracker keeps its keyframes until it came
    live_sets += ['tracker.keep_for=["mapper"]'] if live else []
    if prior_map:  # `--map`: the tracker's saved map, read here first so a bad one stops the run before it starts
        live_sets.append(f"tracker.map={map_path(prior_map).resolve()}")
    cfgs = _resolve_configs(source, config, _split_overrides(live_sets + (overrides or []), live=live))
    replay_cfg = cfgs["replay"]
    feed_tracker = replay_cfg.play == "tracker"  # a log player stands in for the tracker
    if duration_s and not live:
        raise ConfigError(f"--duration {duration_s}: only for a live source ({', '.join(LIVE_SOURCES)}); "
                          "a file source takes --set replay.end_s=S")
    # opened here to fail fast, before any process starts
    src = LiveSource(source) if live else open_source(source, only_consumed=replay_cfg.only_consumed,
                                                      camera=replay_cfg.camera, every=replay_cfg.every,
                                                      retime=replay_cfg.retime, pair_ms=replay_cfg.pair_ms,
                                                      keyframes_only=feed_tracker)
    cfgs["tracker"] = for_source(cfgs["tracker"], src)  # an unset rolling shutter: the source's camera
    if cfgs["tracker"].map:
        check_prior(cfgs["tracker"].map, src, source)
        cfgs["mapper"] = prior_mapper(cfgs["mapper"], map_path(cfgs["tracker"].map).parent)
    if live and not any(o.split("=", 1)[0].strip() == "recorder.publish_lag_ms" for o in overrides or []):
        # the camera holds back only what the tracker would skip: a burst within its lag it tracks in order
        cfgs["recorder"] = dataclasses.replace(cfgs["recorder"], publish_lag_ms=cfgs["tracker"].live_lag_ms)
    cfgs["mapper"], map_frame = _map_frame(cfgs["mapper"], src,
                                           imu=cfgs["tracker"].imu and not isinstance(src, LiveSource)
                                           and has_imu(src))
    if router is not None and (why := router_unreachable(router)) is not None:  # before any file is written
        raise ConfigError(f"--router {router}: {why}; start one first (`octolog router --listen {router}`) "
                          "or leave --router out (the run hosts its own)")
    prepare_out(out, overwrite=overwrite)
    marker = out / INCOMPLETE
    # written first, removed last: even a kill -9 of this process leaves the folder marked
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    marker.write_text(f"octolog run has not finished writing this session (started {started}, pid {os.getpid()}); "
                      f"if no run is going on, it failed or was killed\n")
    try:
        rec = cfgs.get("recorder")
        if isinstance(src, LiveSource) and rec.backend == "software" and rec.software.scene == "room":
            # the simulated camera's frames rendered before any stage starts; its path is the ground truth
            src.groundtruth = simcamera.prepare(rec, duration_s, quiet=quiet).groundtruth_tum()
        summary = _run(SessionPlan(source, out, src, cfgs, feed_tracker, rerun, recording_id, quiet, duration_s,
                                   router, ros2_domain, map_frame))
    except BaseException as exc:
        what = str(exc) if isinstance(exc, OctologError) else \
            ("interrupted" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}")
        try:
            marker.write_text(f"octolog run failed: {what}\n")
        except OSError:
            pass  # the marker from the start stays: "has not finished"
        raise
    marker.unlink()
    return summary


@dataclass(frozen=True)
class SessionPlan:
    """What one `octolog run` session is, resolved before any process starts."""

    source: str
    out: Path
    src: Source | LiveSource
    cfgs: dict[str, Any]  # stage -> its validated config (Any: one config class per stage, each read by name)
    feed_tracker: bool  # a log player stands in for the tracker
    rerun: str
    recording_id: str
    quiet: bool
    duration_s: float = 0.0
    router: str | None = None  # join this router; None: host one on a free loopback port
    ros2_domain: int = -1
    map_frame: dict[str, str] | None = None  # where up came from (see _map_frame)

    @property
    def live(self) -> bool:
        return isinstance(self.src, LiveSource)

    @property
    def log_compression(self) -> str:
        """The session log's chunks: uncompressed when the frames travel encoded (lz4 gained ~1 % on
        PNG/JPEG frames at half the logger's CPU), lz4 when they travel raw."""
        if self.live:
            encoded = self.cfgs["recorder"].color_codec == "jpeg"  # with depth as zstd
        else:
            wire = self.cfgs["replay"].wire_compression
            encoded = wire not in (SOURCE, "", "raw") or (wire == SOURCE and self.src.encoded)
        return "none" if encoded else "lz4"


def _write_session_files(plan: SessionPlan) -> Path:
    """groundtruth.txt (when the source has one), config.toml and metadata.json; config.toml's path."""
    out, cfgs = plan.out, plan.cfgs
    gt = plan.src.groundtruth_tum()
    if gt:
        (out / "groundtruth.txt").write_text(gt)
    config_path = out / "config.toml"
    config_path.write_text(to_toml({k: to_dict(v) for k, v in cfgs.items()}))
    metadata = {"octolog": {"version": __version__, "source": plan.source, "recording_id": plan.recording_id},
                "config": {k: json.dumps(to_dict(v), sort_keys=True) for k, v in cfgs.items()}}
    if gt:
        metadata["groundtruth"] = {"tum": gt}
    if plan.map_frame:
        metadata["gravity"] = plan.map_frame
    (out / "metadata.json").write_text(json.dumps(metadata, indent=2, sort_keys=True))
    return config_path


def _start_stages(children: StageProcesses, plan: SessionPlan, endpoint: str, rerun: str, config_path: Path) -> None:
    """The session logger, mapper, tracker and the frames' source (replay, or the recorder live)."""
    out = plan.out
    bus = ["--mode", "peer", "--connect", endpoint, "--no-multicast", "--ros2-domain", str(plan.ros2_domain)]
    viz = ["--rerun", rerun, "--recording-id", plan.recording_id]
    conf = ["--config", str(config_path)]
    producers = "tracker,mapper" if plan.feed_tracker else ("recorder" if plan.live else "replay") + ",tracker,mapper"
    children.start("log", ["log", *bus, "--out", str(out / "session.mcap"), "--metadata", str(out / "metadata.json"),
                           "--compression", plan.log_compression, "--stages", producers])
    children.start("mapper", ["map", *bus, *viz, *conf, "--out", str(out)])
    if not plan.feed_tracker:
        children.start("tracker", ["track", *bus, *viz, *conf, "--trajectory", str(out / "trajectory.txt"),
                                    "--save-map", str(out / MAP_FILENAME)])
    quiet_flag = [] if not plan.quiet else ["--quiet"]
    if plan.live:  # the camera in full to recording.mcap; its images reach Rerun through the tracker
        children.start("recorder", ["record", str(out / "recording.mcap"), "--publish", *bus, "--rerun", "off",
                                    *conf, "--duration", str(plan.duration_s), *quiet_flag], show_stderr=not plan.quiet)
    else:
        children.start("replay", ["replay", *bus, *viz, *conf, *quiet_flag], show_stderr=not plan.quiet)


def _run(plan: SessionPlan) -> SessionSummary:
    rerun = f"save:{plan.out / 'rerun'}" if plan.rerun == "save" else plan.rerun
    kind, viewer = parse_spec(rerun)
    viewer = viewer or DEFAULT_VIEWER
    # streamed to a viewer, each stage's recording is saved in OUT/rerun as well: a viewer that is
    # not there (or closed part-way) costs nothing of the session; one that is not there at the
    # start is not waited for at all
    missed = viewer_unreachable(viewer) if kind == "connect" else None
    if missed is not None:
        log.warning("no Rerun viewer at %s (%s): the stages' recordings are saved in %s instead; "
                    "`octolog view %s` opens them", viewer, missed, plan.out / "rerun", plan.out)
        rerun = f"save:{plan.out / 'rerun'}"
    copy = {COPY_ENV: str(plan.out / "rerun")} if kind == "connect" else {}
    with HostedRouter(plan.router) as router:
        config_path = _write_session_files(plan)
        children = StageProcesses(plan.out / "logs", env=copy)
        t0 = time.monotonic()
        try:
            _start_stages(children, plan, router.endpoint, rerun, config_path)
            router.ready()
            finishing = Finishing(children, live=plan.live, quiet=plan.quiet)
            children.wait_all(finishing.done, finishing.waiting)
        finally:
            children.stop_all()
            children.end_line()
        wall = time.monotonic() - t0
    return _summarize(plan.out, plan.source, plan.src, wall, plan.recording_id, loop=plan.cfgs["replay"].loop,
                      viewer_missed=None if missed is None else {"url": viewer, "reason": missed,
                                                                 "saved": str(plan.out / "rerun")})


def _keep_live_up(out: Path, found: dict) -> None:
    """The up the mapper found (a live camera's accelerometer, the tracker's IMU), into the
    session's config.toml and metadata.json: a replay of the session then draws the same grid."""
    config = tomllib.loads((out / "config.toml").read_text())
    config.setdefault("mapper", {})["grid_up"] = [float(v) for v in found["up"]]
    (out / "config.toml").write_text(to_toml(config))
    meta_path = out / "metadata.json"
    metadata = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    metadata["gravity"] = {"up": json.dumps([float(v) for v in found["up"]]), "note": str(found["note"])}
    meta_path.write_text(json.dumps(metadata, indent=2, sort_keys=True))


def camera_frames(recording: Path) -> int:
    """RGB-D frames a live camera delivered: colour with aligned depth, counted in its recording."""
    counts = message_counts(recording) or {}
    colour = counts.get(T.COLOR.name, 0) + counts.get(T.COLOR_JPEG.name, 0)
    return min(colour, counts.get(T.ALIGNED_DEPTH.name, 0) + counts.get(T.ALIGNED_DEPTH_PNG.name, 0))


def frame_counts(log: Path, camera: int | None = None, tally: dict | None = None) -> tuple[dict[str, int], int]:
    """What the session log says about frames: published, consumed by the tracker, skipped; and the
    sensor time between the first and the last frame the tracker consumed (its statuses' stamps:
    what a replay played, a start/end window or loops included; 0 without statuses). One pass over
    the log, or none with the logger's `tally` of the statuses it wrote (recorder/buslog.py:
    StatusTally, in its report) and a complete file. With the frames a live camera delivered
    (`camera`), the ones it did not publish count as skipped too (`held_back`: the tracker had
    RecorderConfig.publish_window frames in hand, or the recorder's live queue was full; the
    recorder's own summary line tells the two apart)."""
    published = 0
    counts = message_counts(log)  # the frames counted from the summary: not read (they are gigabytes)
    frame_topics = [] if counts is not None else [RGBD.name, RGBD_COMPRESSED.name]
    if counts is not None:
        published = counts.get(RGBD.name, 0) + counts.get(RGBD_COMPRESSED.name, 0)
    kept = StatusTally(**tally) if tally is not None else None
    if kept is not None and kept.consumed + kept.skipped == (counts or {}).get(TRACKING_STATUS.name, -1):
        statuses, status_topics = kept, []  # the logger counted them as it wrote them: not read back
    else:
        statuses, status_topics = StatusTally(), [TRACKING_STATUS.name]
    topics = [*frame_topics, *status_topics]
    for m in read_wire(log, topics) if topics else ():
        if m.topic == TRACKING_STATUS.name:
            statuses.add(codec.decode(m.data, TRACKING_STATUS.msgtype))
        else:
            published += 1
    consumed, skipped, span_ns = statuses.consumed, statuses.skipped, statuses.last_ns - statuses.first_ns
    if camera is None:
        return {"published": published, "consumed": consumed, "skipped": skipped}, span_ns
    held_back = max(0, camera - published)
    return ({"camera": camera, "published": published, "consumed": consumed, "skipped": skipped + held_back,
             "held_back": held_back}, span_ns)


def played_ns(duration_ns: int, frames: int, loop: int) -> int:
    """Sensor time a replay plays: the source's span, `loop` times, each later pass one frame interval
    after the one before (as replay/node.py: looped moves time on)."""
    if loop <= 1:
        return duration_ns
    gap = duration_ns // (frames - 1) if frames > 1 else 33_333_333
    return loop * duration_ns + (loop - 1) * gap


def _summarize(out: Path, source: str, src: Source | LiveSource, wall: float, recording_id: str, *,
               loop: int = 1, viewer_missed: dict | None = None) -> SessionSummary:
    live = isinstance(src, LiveSource) and (out / "recording.mcap").exists()
    if isinstance(src, LiveSource):  # how long the camera ran: its recording's span (its summary, not a scan)
        src.duration_ns = _live_span_ns(out, live)
    frames, status_span_ns = frame_counts(out / "session.mcap", camera_frames(out / "recording.mcap") if live else None,
                                          errorfile.read_finding(out / "logs" / "log.report.json", "statuses"))
    played = src.duration_ns if isinstance(src, LiveSource) else \
        (status_span_ns or played_ns(src.duration_ns, len(src), loop))
    s = SessionSummary(out=out, source=source, wall_s=wall, duration_s=played * 1e-9, frame_counts=frames)
    s.map = json.loads((out / "map_stats.json").read_text())
    if "map_frame" in s.map:  # the mapper found up: a live camera's accelerometer, the tracker's IMU
        _keep_live_up(out, s.map["map_frame"])
    if (out / "metadata.json").exists():
        s.map_frame = json.loads((out / "metadata.json").read_text()).get("gravity", {}).get("note", NOT_ALIGNED)
    tracked_any = (out / "trajectory.txt").exists() and any(
        line.strip() and not line.startswith("#") for line in (out / "trajectory.txt").read_text().splitlines())
    if tracked_any:  # no file: the tracker was fed from a log; an empty one: every frame LOST (said below)
        traj = metrics.read_tum(out / "trajectory.txt")
        s.frames = len(traj.stamps_ns)
        if (out / "groundtruth.txt").exists():
            try:
                a = metrics.ate(traj, metrics.read_tum(out / "groundtruth.txt"))
                s.ate = {"rmse_m": a.rmse, "mean_m": a.mean, "max_m": a.max, "pairs": a.n_pairs}
            except InputError as exc:  # two poses, or all on a line: no alignment, but the run is whole
                s.ate_note = str(exc)
    s.files = {p.name: str(p) for p in sorted(out.glob("*")) if p.is_file() and p.name != INCOMPLETE}
    s.files.update({f"rerun/{p.name}": str(p) for p in sorted((out / "rerun").glob("*.rrd"))})
    s.files["summary.json"] = str(out / "summary.json")
    # samples the stages' buses dropped as malformed (not messages, or lying about their sizes)
    s.malformed = {p.name.removesuffix(".report.json"): counts for p in sorted((out / "logs").glob("*.report.json"))
                   if (counts := errorfile.read_malformed(p))}
    # where each stage's CPU went (kit/cpuclock.py); CPU time differs run to run: not for comparing outputs
    cpu = {p.name.removesuffix(".report.json"): errorfile.read_cpu(p) for p in sorted((out / "logs").glob("*.report.json"))}
    s.depth_bias = errorfile.read_finding(out / "logs" / "tracker.report.json", "depth_bias")
    s.prior_map = errorfile.read_finding(out / "logs" / "tracker.report.json", "prior_map")
    s.imu = errorfile.read_finding(out / "logs" / "tracker.report.json", "imu")
    if s.imu and (s.imu.get("noise_measured") or s.imu.get("camera_from_imu") or s.imu.get("late_ms")):
        (out / "imu.toml").write_text(imu_keys(np.array(s.imu["camera_from_imu"]) if s.imu.get("camera_from_imu") else None,
                                               -float(s.imu.get("late_ms", 0.0)),
                                               ImuNoise(*s.imu["noise_measured"]) if s.imu.get("noise_measured") else None))
        s.files["imu.toml"] = str(out / "imu.toml")
    s.uninitialised = errorfile.read_finding(out / "logs" / "tracker.report.json", "uninitialised")
    s.movers = s.map.get("movers")
    s.viewer_missed = viewer_missed or next((found for p in sorted((out / "logs").glob("*.report.json"))
                                             if (found := errorfile.read_finding(p, "viewer_missed"))), None)
    (out / "summary.json").write_text(json.dumps(
        {"source": source, "frames": frames, "tracked_frames": s.frames, "wall_s": round(wall, 3),
         "malformed": s.malformed, "map_frame": s.map_frame, "cpu_s": cpu, "depth_bias": s.depth_bias, "prior_map": s.prior_map,
         "imu": s.imu, "uninitialised": s.uninitialised, "viewer_missed": s.viewer_missed, "movers": s.movers,
         "duration_s": s.duration_s, "ate": s.ate, "map": s.map, "files": sorted(s.files),
         "recording_id": recording_id, "versions": versions()},
        indent=2, sort_keys=True) + "\n")
    return s


def _live_span_ns(out: Path, recorded: bool) -> int:
    """How long a live camera ran: its recording's span from the file's summary, else (no recording,
    or one without a summary) the span of the frames in the session log, which takes a whole scan."""
    if recorded and (span := time_span(out / "recording.mcap")) is not None:
        return span[1] - span[0]
    t = next((t for name, t in summarize(out / "session.mcap").topics.items() if name in (RGBD.name,
              RGBD_COMPRESSED.name)), None)
    return t.last_ns - t.first_ns if t is not None else 0


def skipped_line(frames: dict) -> str:
    """The frames a live tracker did not take (`frame_counts`): it takes what it keeps up with, so the
    user sees how much of the stream that was and where the rest stayed."""
    held = frames.get("held_back", 0)
    parts = [f"{held} held back by the camera while the tracker had frames in hand"] if held else []
    if frames["skipped"] > held:
        parts.append(f"{frames['skipped'] - held} skipped by the tracker")
    total = frames.get("camera", frames["published"])
    source = "the camera's" if "camera" in frames else "the published"
    return (f"frames: the tracker took {frames['consumed']} of {source} {total}, kept up with "
            f"{100 * frames['consumed'] / max(total, 1):.0f} % ({'; '.join(parts)})")


def format_summary(s: SessionSummary) -> str:
    """The summary `octolog run` prints: frames and rate, ATE, map, files."""
    lines = [f"session {s.out}: {s.frames} frames from {s.source} in {s.wall_s:.1f} s "
             f"(real-time factor {s.duration_s / s.wall_s if s.wall_s else 0:.2f})"]
    if s.frame_counts.get("skipped"):
        lines.append("  " + skipped_line(s.frame_counts))
    if not s.frames and (s.out / "trajectory.txt").exists():
        lines.append(f"  no frame tracked: every frame LOST (the tracker's count: {s.out / 'logs' / 'tracker.log'}), "
                     "so nothing is mapped")
        if s.uninitialised:
            lines.append("  tracker " + uninitialised_line(s.uninitialised))
    if s.ate_note:
        lines.append(f"  ATE: none ({s.ate_note})")
    if s.ate:
        lines.append(f"  ATE RMSE {s.ate['rmse_m'] * 100:.2f} cm (mean {s.ate['mean_m'] * 100:.2f} cm, "
                     f"max {s.ate['max_m'] * 100:.2f} cm, {s.ate['pairs']} poses)")
    m = s.map
    lines.append(f"  map: {m.get('keyframes', 0)} keyframes, {m.get('occupied_voxels', 0)} occupied / "
                 f"{m.get('free_voxels', 0)} free voxels at {m.get('resolution_m', 0) * 100:.0f} cm, {m.get('cloud_points', 0)} cloud points")
    lines.append(f"  map frame: {s.map_frame}")
    lines.append("  " + imu_line(s.imu))
    if s.depth_bias:
        lines.append(depth_bias_line(s.depth_bias))
    if s.prior_map:
        lines.append("  " + prior_line(s.prior_map))
    if s.movers:
        lines.append("  " + movers_line(s.movers))
    if s.viewer_missed:
        lines.append(f"  viewer: not reachable at {s.viewer_missed.get('url')}; the stages' recordings are in "
                     f"{s.out / 'rerun'} (`octolog view {s.out}`)")
    for stage, counts in s.malformed.items():
        lines.append(f"  {stage} dropped malformed samples: " + ", ".join(f"{n} on {t}" for t, n in counts.items()))
    lines.append("  files: " + ", ".join(sorted(s.files)))
    return "\n".join(lines)


STAGE_CHOICES = {("tracker", "mapper"): "camera", ("mapper",): "tracker"}


def replay_session(session: Path, *, out: Path, stages: tuple[str, ...] = ("tracker", "mapper"),
                   overrides: list[str] | None = None, rerun: str = "save", recording_id: str,
                   quiet: bool = False, overwrite: bool = False) -> SessionSummary:
    """Re-run stages of a recorded session from its log, with the session's own configuration.

    `stages` run fresh; the others are fed from the log. tracker+mapper: the frames the live tracker
    consumed, in lockstep; mapper alone: the logged keyframes and pose corrections.
    """
    key = tuple(s for s in ("tracker", "mapper") if s in stages)
    if key not in STAGE_CHOICES or set(stages) - {"tracker", "mapper"}:
        raise ConfigError(f"--stages {','.join(stages)}: want tracker,mapper or mapper (= --from tracker)")
    if (why := not_a_session(session)) is not None:
        raise InputError(why)
    why = incomplete_reason(session)
    if why is not None:
        raise InputError(f"{session}: an incomplete session ({INCOMPLETE}: {why}); run it again, "
                         f"or `octolog info {session}` for what its log holds")
    log, config = session / "session.mcap", session / "config.toml"
    missing = [p.name for p in (log, config) if not p.is_file()]
    if missing:
        can = "nothing (the log holds every input)" if "session.mcap" in missing else \
            f"the stages with default settings: octolog run --source mcap:{log}"
        raise InputError(f"{session}: missing {', '.join(missing)}; what can still be replayed: {can}")
    s = summarize(log)
    if not s.complete:
        n = sum(t.count for t in s.topics.values())
        raise InputError(f"{log}: truncated ({s.problem}); {n} messages are readable: "
                         f"`octolog info {log}` lists them, a byte-exact replay needs the whole log")
    feed = STAGE_CHOICES[key]
    fixed = [f"replay.play={feed}", "tracker.live=false", "tracker.throttle_ms=0.0"]
    if feed == "camera":
        fixed.append("replay.only_consumed=true")
        # where the live tracker's keyframes went in without waiting for the back end: the same here
        fixed.append(f"tracker.backend_deferred={sorted(backend_deferred(log))}")
    return run_session(source=f"mcap:{log}", out=out, config=str(config), overrides=fixed + list(overrides or []),
                       rerun=rerun, recording_id=recording_id, quiet=quiet, overwrite=overwrite)


def merge_rrd(session: Path) -> Path:
    """Merge a session's per-stage .rrd files into `session.rrd` (one recording, one timeline)."""
    if (why := not_a_session(session)) is not None:
        raise InputError(why)
    parts = sorted((session / "rerun").glob("*.rrd"))
    parts = [p for p in parts if p.name != "session.rrd"]
    if not parts:
        raise InputError(f"{session / 'rerun'}: no .rrd files (was the session run with --rerun off?)")
    out = session / "rerun" / "session.rrd"
    rerun = Path(sys.executable).with_name("rerun")
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1"}
    with open(out, "wb") as f:
        proc = subprocess.run([str(rerun), "rrd", "merge", *map(str, parts)], stdout=f, stderr=subprocess.PIPE,
                              env=env, text=True)
    if proc.returncode != 0:
        raise StageError(f"rerun rrd merge failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr else ''}")
    return out
