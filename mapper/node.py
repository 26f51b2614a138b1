"""The mapper process: keyframes and pose corrections in; map snapshots on the bus; map files out."""

from __future__ import annotations

import time
from pathlib import Path

from octolog.kit.bus import Bus, BusConfig, Publisher, Received
from octolog.kit.config import to_dict
from octolog.kit.cpuclock import charge
from octolog.kit.errors import InputError, MapError
from octolog.kit.viz import Viz
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import Mapper, make_mapper
from octolog.mapper.fleet.follow import run_follower
from octolog.mapper.fleet.node import run_fleet
from octolog.mapper.mapframe import MapFrame
from octolog.mapper.prior import PriorSeed
from octolog.mapper.process import INBOX_KEYFRAMES, MapperResult, MapSnapshots, answer_save, finish, log_map
from octolog.schemas import codec, posemsgs, rgbdmsgs, streammsgs
from octolog.schemas.msgtypes import OctomapMsg
from octolog.schemas.topics import (
    CONFIGS,
    KEYFRAME,
    KEYFRAME_COMPRESSED,
    KEYFRAME_END,
    KEYFRAME_POSES,
    MAP_QUERY,
    MAP_SAVE,
    MAP_UPDATE,
    TRACKER_GRAVITY,
)

MOVER_COLOUR = (230, 40, 40)  # the viewer's `map/movers` layer


def run(cfg: MapperConfig, bus_cfg: BusConfig, *, out_dir: Path, rerun: str = "off",
        recording_id: str = "octolog") -> MapperResult:
    """The mapper process: consume keyframes until the tracker's stream ends, then write the map."""
    if cfg.robots:
        fleet = run_follower if cfg.follow else run_fleet
        return fleet(cfg, bus_cfg, out_dir=out_dir, rerun=rerun, recording_id=recording_id)
    mapper = make_mapper(cfg)
    prior = PriorSeed(cfg.prior) if cfg.prior else None  # before the bus: a bad prior stops nothing running
    with Bus(bus_cfg, cfg.stage, inbox_size=INBOX_KEYFRAMES) as bus, Viz(rerun, "mapper", recording_id) as viz:
        publisher = MapSnapshots(bus, mapper, cfg.publish_every)
        publisher.frame = MapFrame(mapper, bus, viz, from_imu=not cfg.grid_up)
        result = consume(mapper, cfg, bus, viz, publisher, out_dir, prior)
        publisher.frame.resolve()  # before the last snapshot, if none came before it
        found = publisher.frame.found
        extra = ({"map_frame": found} if found else {}) | \
            ({"prior": cfg.prior, "prior_keyframes": prior.taken, "prior_note": prior.note} if prior else {})
        finish(mapper, result, bus, viz, publisher, out_dir, extra or None)
    return result


def consume(mapper: Mapper, cfg: MapperConfig, bus: Bus, viz: Viz, publisher: MapSnapshots,
            out_dir: Path, prior: PriorSeed | None = None) -> MapperResult:
    """Integrate keyframes and corrections until every one the tracker announced has arrived; with
    a `prior`, the earlier session's map first if the tracker's first item says it tracks in it."""
    pub_update = bus.publisher(MAP_UPDATE)
    bus.accept(MAP_SAVE)
    bus.start([KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_POSES, KEYFRAME_END, TRACKER_GRAVITY], wait_for=cfg.wait_for,
              timeout_s=cfg.wait_timeout_s)
    bus.publisher(CONFIGS["mapper"]).put(streammsgs.config_msg("mapper", to_dict(cfg)))
    bus.watch(["tracker"])
    result = MapperResult()
    expected: int | None = None
    received = 0
    # the tracker ends its corrections (keyframe_poses) before its keyframes, on one publisher
    expected_poses, received_poses = 0, 0
    while expected is None or received < expected or received_poses < expected_poses:
        r = bus.receive()
        if r is None:
            if expected is not None:
                bus.expect_count(KEYFRAME, received, expected)
                bus.expect_count(KEYFRAME_POSES, received_poses, expected_poses)
            continue
        if r.topic == KEYFRAME_END:
            end = r.decode()
            if end.topic == KEYFRAME_POSES.name:
                expected_poses = int(end.count)
                continue
            if end.topic not in (KEYFRAME.name, KEYFRAME_COMPRESSED.name):
                continue  # the end of a stream the mapper does not take (tracker/trajectory)
            expected = int(end.count)
            bus.expect_count(KEYFRAME, received, expected)
            bus.unwatch("tracker")
            continue
        if r.topic == MAP_SAVE:
            answer_save(r, mapper, out_dir)
            continue
        if r.topic == TRACKER_GRAVITY:
            if publisher.frame is not None:
                publisher.frame.from_tracker(r.decode())
            continue
        if prior is not None and prior.pending:
            _decide(prior, mapper, publisher, r.decode().id if r.topic in (KEYFRAME, KEYFRAME_COMPRESSED) else None)
        if r.topic == KEYFRAME_POSES:
            received_poses += 1
            try:
                msg = r.decode()
                result.corrections += mapper.correct(posemsgs.keyframe_poses_from_msg(msg), msg.depth_inverse_offset)
            except InputError as exc:  # the whole correction is refused; the map is unchanged
                result.problems.append(str(exc))
            continue
        received += 1
        _integrate_keyframe(r, mapper, result, viz, publisher, pub_update)
    if prior is not None and prior.pending:  # no keyframe, no correction (localizing): the earlier map
        _decide(prior, mapper, publisher, None)
    return result


def _decide(prior: PriorSeed, mapper: Mapper, publisher: MapSnapshots, first_keyframe_id: int | None) -> None:
    if prior.decide(mapper, first_keyframe_id) and prior.up is not None and publisher.frame is not None:
        publisher.frame.use(prior.up, f"the map frame of {prior.folder} (mapper.prior)")
        publisher.frame.given = True


def _integrate_keyframe(r: Received, mapper: Mapper, result: MapperResult, viz: Viz, publisher: MapSnapshots,
                        pub_update: Publisher) -> None:
    """One keyframe into the map (a bad one counted and skipped), its map update out, a snapshot when due."""
    t0 = time.perf_counter()
    msg = r.decode()
    stamp = codec.stamp_ns(msg.header)
    try:
        kf_id, pose, frame = rgbdmsgs.keyframe_from_msg(msg)
        if publisher.frame is not None:
            publisher.frame.first_keyframe(frame)
        with charge("mapper"):
            n = mapper.integrate(kf_id, pose, frame)
        result.keyframes += 1
    except (InputError, MapError) as exc:
        # a bad keyframe is counted, reported and skipped; the map is never touched by it
        result.skipped += 1
        result.problems.append(str(exc))
        kf_id, n, frame = int(msg.id), 0, None
    ms = (time.perf_counter() - t0) * 1e3
    result.ms.append(ms)
    pub_update.put(codec.msgtype(MAP_UPDATE.msgtype)(
        header=codec.header(stamp, "world"), keyframe_id=kf_id, n_points=n,
        # voxel counts as of the last snapshot: counting every keyframe costs more than integrating it
        n_occupied=publisher.stats.get("occupied_voxels", 0), n_free=publisher.stats.get("free_voxels", 0),
        processing_ms=ms))
    if frame is not None:
        with charge("mapper"):
            publisher.maybe(result.keyframes, stamp)
        if viz.enabled:
            viz.set_time(stamp, frame.seq)
            viz.scalar("mapper/ms", ms)
            # this keyframe's movers: the voxels whose hits were kept out of the map (empty: none)
            viz.boxes("map/movers", mapper.last_masked, mapper.resolution_m, MOVER_COLOUR)
            if publisher.every and result.keyframes % publisher.every == 0:
                log_map(viz, mapper, stamp, publisher.grid)


def fetch_map(bus: Bus, timeout_s: float = 10.0) -> OctomapMsg | None:
    """What a late joiner does: ask the mapper's queryable for the current map."""
    return bus.fetch(MAP_QUERY, timeout_s)
