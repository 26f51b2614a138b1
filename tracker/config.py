"""Tracker settings: `TrackerConfig` (the `[tracker]` table and `--set tracker.…`), validated once, and
`OdometryParams`, the native core's whole parameter object built from it.

The switches and sizes people tune (`n_features`, `local_ba`, `ba_window`, ...) are top-level keys;
every other tunable of the native core sits in a section named after the stage that uses it
(`tracker.features.grid_cols`, `tracker.loops.min_votes`, ...). Defaults live here only: they are
the values measured on TUM fr1/xyz at 640x480, and changing one changes the outputs.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, replace
from typing import ClassVar

from octolog.kit.depthmodel import DepthModel
from octolog.kit.errors import ConfigError
from octolog.schemas.wirecompression import parse_wire_compression

MODES = ("map", "localize")
ENGINES = ("native", "orbslam3")


@dataclass(frozen=True)
class FeatureParams:
    """ORB extraction (tracker.features.OrbExtractor); `n_features` is a top-level key."""

    grid_cols: int = 8  # keypoints are spread over a grid of cells ...
    grid_rows: int = 6  # ... this many rows of them
    fast_threshold: int = 20  # FAST corner threshold ...
    min_fast_threshold: int = 7  # ... lowered to this in cells where the first finds too few
    n_levels: int = 8  # image pyramid levels
    scale_factor: float = 1.2  # scale between pyramid levels (also a keypoint's pixel sigma per level)


@dataclass(frozen=True)
class DepthParams:
    """Which depth readings keypoints take (tracker.features.lookup_depth)."""

    min_m: float = 0.2  # readings nearer than this are ignored
    max_m: float = 6.0  # readings farther than this are ignored
    max_new_point_m: float = 4.0  # a keyframe makes map points only from readings up to this range
    # a reading whose 3x3 neighbourhood spreads more than this fraction of it sits on an edge: ignored
    edge_spread: float = 0.04
    # the camera's systematic depth error, corrected in every reading: 1/z <- 1/z - inverse_offset
    # (1/m; > 0: the camera reads short, by inverse_offset * z^2 m at z). A session's own estimate is
    # in summary.json `depth_bias` (tracker/depth_bias.py); a disparity offset of d px is d / (f b).
    inverse_offset: float = 0.0
    # estimate the bias from the map while tracking and correct it (on top of inverse_offset) once
    # the estimate is confident, the map with it (tracker/depth_correction.py)
    correct_bias: bool = False


@dataclass(frozen=True)
class TrackingParams:
    """Matching the local map and fitting the pose, per frame."""

    search_radius_px: float = 15.0  # match window around the motion model's prediction (x3 if weak)
    refine_radius_px: float = 4.0  # match window around the first pose, for the second pass
    max_hamming: int = 80  # descriptor distance limit of a projected match
    match_ratio: float = 0.9  # best/second-best distance ratio of a projected match
    # a pose with this share of its matches as inliers (and 3 x min_inliers) ends the search early
    confident_ratio: float = 0.5
    ransac_reproj_px: float = 4.0  # PnP RANSAC inlier threshold
    ransac_iterations: int = 100  # PnP RANSAC iterations
    # sigma of an inverse-depth residual (1/m) in the pose fit: weighs depth against pixels
    inv_depth_sigma: float = 0.03
    # young points (no keyframe has matched them again) that move the camera's fit more than this
    # away from the established points' own fit, and beyond chance, pull it (a person walking by):
    # the established fit is kept (tracker/map_tracking.py). A person moves ~3 cm a frame; the
    # newest keyframe's own small errors shift it a few mm on real data (fr1/xyz: up to 7 mm). 0: off
    young_pull_m: float = 0.01
    min_inliers: int = 20  # fewer inliers: the frame is LOST
    # after LOST, a pose found again with fewer inliers stays LOST (ORB-SLAM's relocalisation threshold)
    relocalise_min_inliers: int = 50
    # a pose that leaves the constant-velocity prediction by more than these (per frame at 30 fps,
    # growing with the square of a longer interval) on fewer than `jump_support` inliers is a jump
    # the motion cannot explain, from too little evidence: the frame is LOST, not published (on fast
    # turns with 30 ms of blur such frames were 6-29 cm off; no real hand-held step was caught)
    max_jump_m: float = 0.07
    max_jump_deg: float = 3.0
    jump_support: int = 150
    # keypoints with depth a frame needs to start the map, or to become a keyframe
    min_init_points: int = 100


@dataclass(frozen=True)
class KeyframeParams:
    """When a tracked frame becomes a keyframe (any one of these)."""

    # Pose change (a backstop: on fast motion a keyframe every 6 cm / 6 degrees was one every 3.5
    # frames, with a local BA behind each; see docs/results.md for how 8 / 8 was chosen)
    translation_m: float = 0.08  # moved this far from its reference keyframe (tracker.keyframe_map)
    rotation_deg: float = 45.0  # turned this far from it
    # shares less than this fraction of the points the reference shared with the first frame it served
    min_overlap: float = 0.5
    # ORB-SLAM's rule for depth cameras: tracks fewer than this many map points nearer than
    # depth.max_new_point_m while more than `close_untracked` such keypoints are not in the map
    close_tracked: int = 100
    close_untracked: int = 70


@dataclass(frozen=True)
class LocalMapParams:
    """The map points a frame is matched against, and which points are kept."""

    n_keyframes: int = 8  # keyframes nearest to the pose (by position and viewing direction) ...
    n_recent_keyframes: int = 2  # ... always including the newest this many
    cull_min_visible: int = 12  # a point in view this often ...
    cull_min_found_ratio: float = 0.2  # ... but matched less than this share of those times is retired
    fuse_depth: bool = True  # a keyframe averages its depth readings into the points it matched


@dataclass(frozen=True)
class BundleAdjustmentParams:
    """Local BA at every keyframe (window size: `ba_window`) and the final BA (`global_ba_keyframes`)."""

    fixed_keyframes: int = 6  # earlier keyframes that made most window points, held fixed
    iterations: int = 3  # Levenberg-Marquardt iterations per local BA run
    max_points: int = 800  # local BA keeps the best-observed this many points
    inv_depth_sigma: float = 0.01  # sigma of a depth reading's inverse depth (1/m) in BA
    max_point_move_m: float = 0.05  # a point local BA moves farther was badly observed: retired
    global_iterations: int = 10  # iterations of the final BA at the end of the stream


@dataclass(frozen=True)
class LoopParams:
    """Loop closing (`loop_closing`): candidates, verification, and which corrections are applied."""

    min_gap: int = 10  # keyframes between a loop's ends, and between two closed loops
    min_votes: int = 40  # descriptor votes a candidate keyframe needs to be verified
    min_inliers: int = 40  # 3D-3D inliers a verified loop needs
    min_correction_m: float = 0.02  # smaller corrections (and ...
    min_correction_deg: float = 1.0  # ... turns): the map already agrees, nothing is done
    max_correction_m: float = 2.0  # larger corrections (or ...
    max_correction_deg: float = 45.0  # ... turns) are more than drift can explain: rejected
    # two consecutive keyframes must ask for the same world correction, within these, to close a loop
    consistency_m: float = 0.03
    consistency_deg: float = 1.0


@dataclass(frozen=True)
class OdometryParams:
    """Everything `RgbdSlam` needs, grouped by the part of the core that uses it, and nothing of
    the process around it. Built by `TrackerConfig.odometry_params()`, where it is validated. It has
    no defaults of its own: they live in `TrackerConfig` and its sections (shared with this), the one
    source of them."""

    n_features: int
    features: FeatureParams
    depth: DepthParams
    tracking: TrackingParams
    keyframes: KeyframeParams
    local_map: LocalMapParams
    local_ba: bool
    ba_window: int
    bundle_adjustment: BundleAdjustmentParams
    global_ba_keyframes: int
    loop_closing: bool
    loops: LoopParams
    relocalise: bool
    bow_candidates: int
    readout_s: float  # rolling-shutter readout, first row to last (0: global shutter)
    localize: bool  # tracker.mode = "localize": the saved map is not changed, keyframes are temporary
    map_find_frames: int  # frames a saved map may take to find the camera in (tracker/slam.py: SavedMapSearch)
    map_find_every: int  # while it is looked for, place recognition on every this many frames
    imu: bool  # use the camera's IMU when the stream has one (tracker/imu_fusion.py)
    max_inertial_s: float  # the longest a pose may come from the IMU alone (INERTIAL)


@dataclass(frozen=True)
class TrackerConfig:
    RENAMED: ClassVar[dict[str, str]] = {"backend": "engine"}  # keys of older configs, and their names now

    n_features: int = 1000
    # live: when frames queue up, track the newest and skip the older ones (each skip is published
    # as a SKIPPED status, so the session log says exactly which frames were consumed)
    live: bool = False
    # live: frames are tracked in order while the newest one waiting is at most this much sensor
    # time ahead of the next (three frames at 30 fps: a keyframe and its hand-off to the back end take
    # two to three frame times on two cores, and a tracker that waits one out catches up on the frames
    # after it; at one frame's lag, a live walk's camera held back 13 % of its frames, at three 2-4 %);
    # beyond it every other frame is skipped until the tracker is back within it, and beyond 4 times
    # it the newest wins at once (tracker/node.py: _skip_behind). 0: the newest always wins. The
    # latency a live tracker may add to catch up
    live_lag_ms: float = 100.0
    # live: a keyframe goes in without waiting for a busy back end, at most this many in a row (its
    # result lands at a later keyframe; each such keyframe is on record, tracker/backend_deferred,
    # which `octolog replay` follows); 0: always wait, as a file replay does
    live_backend_defer: int = 4
    # frame numbers at which a replayed live run's keyframes went in without the back end (`octolog
    # replay` sets it from the log's tracker/backend_deferred)
    backend_deferred: tuple[int, ...] = ()
    # pad each frame's processing to at least this long: rehearse a slower machine (0: off)
    throttle_ms: float = 0.0
    # pad each back-end job (in its worker process) to at least this long: a slower back end (0: off)
    backend_throttle_ms: float = 0.0
    # stages that must be up before this one announces itself (e.g. "mapper" when run by hand)
    wait_for: tuple[str, ...] = ()
    wait_timeout_s: float = 60.0
    # stages the tracker keeps its keyframes for at the end of its stream: it waits up to
    # `wait_timeout_s` for one that has not appeared yet (a mapper that joins a live run late), then
    # until it is done (`octolog run` names its mapper; by hand, a mapper that never came is not waited for)
    keep_for: tuple[str, ...] = ()
    # keyframes on the wire: "source" (default): with the images as the frame came (compressed frames
    # give tracker/keyframe/compressed, not re-encoded; raw ones tracker/keyframe); "" or "raw": raw;
    # COLOUR[,DEPTH] with COLOUR jpeg[:QUALITY] or png[:LEVEL], DEPTH png or zstd: re-encoded (see
    # replay.wire_compression)
    wire_compression: str = "source"
    # the SLAM engine: "native" (ours, deterministic) or "orbslam3" (pyorbslam3, an extra: for
    # comparison). "Back end" in the other keys is the native engine's bundle adjustment and loop closing
    engine: str = "native"
    # native back end: local bundle adjustment over the newest `ba_window` keyframes, loop closing
    # (place recognition + pose graph), relocalisation after tracking loss. `background` runs the
    # back end in a worker process; results are applied at the next keyframe either way, so the
    # outputs are byte-identical with it on or off.
    local_ba: bool = True
    ba_window: int = 5
    # the bundle adjustment at the end of the stream: over every keyframe up to this many, else over
    # the newest this many with the keyframes that made their points held (bounded time and
    # memory on long sessions); 0: none
    global_ba_keyframes: int = 500
    loop_closing: bool = True
    relocalise: bool = True
    background: bool = True
    # a DBoW2 text vocabulary (`octolog vocab build`). orbslam3: required (empty:
    # $OCTOLOG_ORB_VOCABULARY); native: optional, a bag-of-words index over it picks loop and
    # relocalisation candidates (else every keyframe is voted on)
    vocabulary: str = ""
    # native, with a vocabulary: the best-scoring this many keyframes are the loop and relocalisation
    # candidates
    bow_candidates: int = 10
    # native: the colour camera's rolling-shutter readout time, first row to last (ms); 0 = global
    # shutter (D455 colour, the synthetic scene). Unset (the default): `octolog run` and the
    # benchmarks take it from the source (TUM freiburg1: 20 ms, see docs/architecture.md), a tracker
    # on the bus from the stream's camera properties (camera/rgbd/properties), else 0.
    rolling_shutter_ms: float | None = None
    # native: a map an earlier session saved (its folder, or its slam_map.npz; `--map`): the tracker
    # finds the camera in it by place recognition and tracks in its world ("": a new map)
    map: str = ""
    # with a map: "map" extends it where the camera sees new places; "localize" only tracks in it
    # (neither the saved map nor the mapper's changes; temporary keyframes carry the camera where
    # the view leaves it, and are never published or saved)
    mode: str = "map"
    # with a map: frames the camera may take to be found in it (LOST meanwhile, tracked in a map of its
    # own that is placed in the saved one when found: 5 s at 30 fps, to walk in from an unmapped
    # doorway); then the tracker says so and goes on in that map of its own (separate, not merged)
    map_find_frames: int = 150
    # with a map, while the camera is not found in it: place recognition against every saved keyframe
    # on one frame in this many (each try costs ~150 ms for 56 keyframes without a vocabulary; the
    # frames between are tracked in the map of its own and placed with it when found)
    map_find_every: int = 3
    # native: fuse the camera's IMU (camera/gyro/sample, camera/accel/sample) when the stream has one:
    # gyro-predicted rotation, biases, gravity and velocity online; false: vision only (a stream
    # without an IMU runs the same either way)
    imu: bool = True
    # native, with an IMU: a frame vision cannot place takes the IMU's pose (INERTIAL) for at most this
    # long after the last one it placed; then LOST
    max_inertial_s: float = 1.5
    # native core, by stage (docs/cli.md lists every key)
    features: FeatureParams = field(default_factory=FeatureParams)
    depth: DepthParams = field(default_factory=DepthParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)
    keyframes: KeyframeParams = field(default_factory=KeyframeParams)
    local_map: LocalMapParams = field(default_factory=LocalMapParams)
    bundle_adjustment: BundleAdjustmentParams = field(default_factory=BundleAdjustmentParams)
    loops: LoopParams = field(default_factory=LoopParams)

    def validate(self) -> None:
        """The one check of every tracker setting; ConfigError names the key."""
        _want(self.engine in ENGINES, "engine", self.engine, f"want one of {', '.join(ENGINES)}")
        _want(self.throttle_ms >= 0, "throttle_ms", self.throttle_ms, "want >= 0")
        _want(self.backend_throttle_ms >= 0, "backend_throttle_ms", self.backend_throttle_ms, "want >= 0")
        _want(self.live_backend_defer >= 0, "live_backend_defer", self.live_backend_defer, "want >= 0 (0: wait)")
        _want(math.isfinite(self.live_lag_ms) and self.live_lag_ms >= 0, "live_lag_ms", self.live_lag_ms,
              "want >= 0 (0: the newest frame always wins)")
        _want(self.wait_timeout_s > 0, "wait_timeout_s", self.wait_timeout_s, "want > 0")
        _want(self.n_features >= 100, "n_features", self.n_features, "want >= 100")
        _want(self.ba_window >= 1, "ba_window", self.ba_window, "want >= 1")
        _want(self.global_ba_keyframes >= 0, "global_ba_keyframes", self.global_ba_keyframes, "want >= 0 (0: none)")
        _want(self.bow_candidates >= 1, "bow_candidates", self.bow_candidates, "want >= 1")
        _want(self.mode in MODES, "mode", self.mode, f"want one of {', '.join(MODES)}")
        _want(self.mode == "map" or bool(self.map), "mode", self.mode, "localize needs a saved map (tracker.map, --map)")
        _want(not self.map or self.engine == "native", "map", self.map, "a saved map needs engine = native")
        _want(self.map_find_frames >= 1, "map_find_frames", self.map_find_frames, "want >= 1")
        _want(self.map_find_every >= 1, "map_find_every", self.map_find_every, "want >= 1")
        _want(0.0 <= self.max_inertial_s <= 10.0, "max_inertial_s", self.max_inertial_s, "want 0 to 10 s")
        if self.rolling_shutter_ms is not None:
            _want(0.0 <= self.rolling_shutter_ms <= 100.0, "rolling_shutter_ms", self.rolling_shutter_ms,
                  "want 0 to 100 (0 = global shutter)")
        try:
            parse_wire_compression(self.wire_compression)
        except ConfigError as exc:
            raise ConfigError(f"tracker.wire_compression: {exc}") from None
        _validate_front_end(self.features, self.depth, self.tracking)
        _validate_local_map(self.keyframes, self.local_map)
        _validate_back_end(self.bundle_adjustment, self.loops)

    def odometry_params(self) -> OdometryParams:
        """The native core's parameters (validated here); an unset rolling shutter is a global one."""
        self.validate()
        return OdometryParams(
            n_features=self.n_features, features=self.features, depth=self.depth, tracking=self.tracking,
            keyframes=self.keyframes, local_map=self.local_map, local_ba=self.local_ba, ba_window=self.ba_window,
            bundle_adjustment=self.bundle_adjustment, global_ba_keyframes=self.global_ba_keyframes,
            loop_closing=self.loop_closing, loops=self.loops, relocalise=self.relocalise,
            bow_candidates=self.bow_candidates, readout_s=(self.rolling_shutter_ms or 0.0) / 1e3,
            localize=self.mode == "localize", map_find_frames=self.map_find_frames,
            map_find_every=self.map_find_every, imu=self.imu,
            max_inertial_s=self.max_inertial_s,
        )


def _want(ok: bool, key: str, value: object, what: str) -> None:
    if not ok:
        raise ConfigError(f"tracker.{key} {value!r}: {what}")


def for_source(cfg: TrackerConfig, source) -> TrackerConfig:
    """`cfg` with an unset rolling_shutter_ms taken from the source's camera (`readout_s`)."""
    if cfg.rolling_shutter_ms is not None:
        return cfg
    return dataclasses.replace(cfg, rolling_shutter_ms=1e3 * float(source.readout_s))


def _validate_front_end(f: FeatureParams, d: DepthParams, t: TrackingParams) -> None:
    """TrackerConfig.validate's checks of feature extraction, depth gating and tracking."""
    _want(f.grid_cols >= 1, "features.grid_cols", f.grid_cols, "want >= 1")
    _want(f.grid_rows >= 1, "features.grid_rows", f.grid_rows, "want >= 1")
    _want(0 < f.min_fast_threshold <= f.fast_threshold, "features.min_fast_threshold", f.min_fast_threshold,
          f"want 1 to features.fast_threshold ({f.fast_threshold})")
    _want(f.n_levels >= 1, "features.n_levels", f.n_levels, "want >= 1")
    _want(f.scale_factor > 1.0, "features.scale_factor", f.scale_factor, "want > 1")
    _want(d.min_m > 0.0, "depth.min_m", d.min_m, "want > 0")
    _want(d.max_m > d.min_m, "depth.max_m", d.max_m, f"want > depth.min_m ({d.min_m}): the range is empty")
    _want(d.max_new_point_m > 0.0, "depth.max_new_point_m", d.max_new_point_m, "want > 0")
    _want(d.edge_spread > 0.0, "depth.edge_spread", d.edge_spread, "want > 0")
    _want(abs(d.inverse_offset) * d.max_m < 0.5, "depth.inverse_offset", d.inverse_offset,
          f"want |value| x depth.max_m < 0.5 (a correction of less than half the reading at {d.max_m:g} m)")
    for key in ("search_radius_px", "refine_radius_px", "ransac_reproj_px", "inv_depth_sigma"):
        _want(getattr(t, key) > 0.0, f"tracking.{key}", getattr(t, key), "want > 0")
    _want(0 <= t.max_hamming <= 256, "tracking.max_hamming", t.max_hamming, "want 0 to 256 (bits)")
    _want(0.0 < t.match_ratio <= 1.0, "tracking.match_ratio", t.match_ratio, "want in (0, 1]")
    _want(0.0 <= t.confident_ratio <= 1.0, "tracking.confident_ratio", t.confident_ratio, "want 0 to 1")
    _want(t.ransac_iterations >= 1, "tracking.ransac_iterations", t.ransac_iterations, "want >= 1")
    _want(t.young_pull_m >= 0.0, "tracking.young_pull_m", t.young_pull_m, "want >= 0 (0: off)")
    _want(t.min_inliers >= 6, "tracking.min_inliers", t.min_inliers, "a pose needs at least 6 inliers")
    _want(t.min_init_points >= 1, "tracking.min_init_points", t.min_init_points, "want >= 1")


def _validate_local_map(k: KeyframeParams, m: LocalMapParams) -> None:
    """TrackerConfig.validate's checks of keyframe decision and the local map."""
    _want(k.translation_m > 0.0, "keyframes.translation_m", k.translation_m, "want > 0")
    _want(k.rotation_deg > 0.0, "keyframes.rotation_deg", k.rotation_deg, "want > 0")
    _want(0.0 <= k.min_overlap <= 1.0, "keyframes.min_overlap", k.min_overlap, "want 0 to 1")
    _want(k.close_tracked >= 0, "keyframes.close_tracked", k.close_tracked, "want >= 0 (0: off)")
    _want(k.close_untracked >= 0, "keyframes.close_untracked", k.close_untracked, "want >= 0")
    _want(m.n_keyframes >= 1, "local_map.n_keyframes", m.n_keyframes, "want >= 1")
    _want(m.n_recent_keyframes >= 1, "local_map.n_recent_keyframes", m.n_recent_keyframes, "want >= 1")
    _want(m.cull_min_visible >= 1, "local_map.cull_min_visible", m.cull_min_visible, "want >= 1")
    _want(0.0 <= m.cull_min_found_ratio <= 1.0, "local_map.cull_min_found_ratio", m.cull_min_found_ratio,
          "want 0 to 1")


def _validate_back_end(b: BundleAdjustmentParams, lp: LoopParams) -> None:
    """TrackerConfig.validate's checks of bundle adjustment and loop closing."""
    _want(b.fixed_keyframes >= 0, "bundle_adjustment.fixed_keyframes", b.fixed_keyframes, "want >= 0")
    _want(b.iterations >= 1, "bundle_adjustment.iterations", b.iterations, "want >= 1")
    _want(b.max_points >= 1, "bundle_adjustment.max_points", b.max_points, "want >= 1")
    _want(b.inv_depth_sigma > 0.0, "bundle_adjustment.inv_depth_sigma", b.inv_depth_sigma, "want > 0")
    _want(b.max_point_move_m > 0.0, "bundle_adjustment.max_point_move_m", b.max_point_move_m, "want > 0")
    _want(b.global_iterations >= 1, "bundle_adjustment.global_iterations", b.global_iterations, "want >= 1")
    _want(lp.min_gap >= 1, "loops.min_gap", lp.min_gap, "want >= 1")
    _want(lp.min_votes >= 0, "loops.min_votes", lp.min_votes, "want >= 0")
    _want(lp.min_inliers >= 6, "loops.min_inliers", lp.min_inliers, "a loop's pose needs at least 6 inliers")
    for key in ("min_correction_m", "min_correction_deg", "consistency_m", "consistency_deg"):
        _want(getattr(lp, key) >= 0.0, f"loops.{key}", getattr(lp, key), "want >= 0")
    _want(lp.max_correction_m > lp.min_correction_m, "loops.max_correction_m", lp.max_correction_m,
          f"want > loops.min_correction_m ({lp.min_correction_m})")
    _want(lp.max_correction_deg > lp.min_correction_deg, "loops.max_correction_deg", lp.max_correction_deg,
          f"want > loops.min_correction_deg ({lp.min_correction_deg})")


def with_depth_model(params: OdometryParams, model: DepthModel) -> OdometryParams:
    """`params` for a camera whose depth error `model` says (kit/depthmodel.py): readings beyond its
    metric range are bearings (no depth residual, no new map point), and no inverse-depth sigma is
    below what the camera measures. The TUM Kinects' and the D455's models change nothing of the
    defaults (metric range 9-14 m, inverse-depth sigma 0.0014-0.0022 1/m); a camera with a short
    baseline or a low resolution does."""
    metric = model.metric_range_m
    d = replace(params.depth, max_m=min(params.depth.max_m, metric),
                max_new_point_m=min(params.depth.max_new_point_m, metric))
    t = replace(params.tracking, inv_depth_sigma=max(params.tracking.inv_depth_sigma, model.inverse_sigma))
    b = replace(params.bundle_adjustment,
                inv_depth_sigma=max(params.bundle_adjustment.inv_depth_sigma, model.inverse_sigma))
    return replace(params, depth=d, tracking=t, bundle_adjustment=b)
