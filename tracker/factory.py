"""The tracker a config names: `make_odometry(cfg)`, native `RgbdSlam` or `OrbSlam3Odometry`.

Apart from tracker.node so that benchmarks and tests build a tracker without the bus and viewer.
"""

from __future__ import annotations

import dataclasses

from octolog.kit.depthmodel import DepthModel
from octolog.tracker.config import TrackerConfig, with_depth_model
from octolog.tracker.interface import Tracker
from octolog.tracker.mapfile import load_map
from octolog.tracker.slam import RgbdSlam
from octolog.tracker.orbslam3 import OrbSlam3Odometry
from octolog.tracker.vocab import load as load_vocabulary
from octolog.tracker.worker import Worker


def make_odometry(cfg: TrackerConfig) -> Tracker:
    """The tracker `cfg.engine` names, set up from `cfg` (ConfigError when `cfg` is invalid)."""
    if cfg.engine == "orbslam3":
        cfg.validate()
        return OrbSlam3Odometry(cfg.vocabulary, n_features=cfg.n_features)
    # native: with a vocabulary, loop and relocalisation candidates come from a bag-of-words index
    params = cfg.odometry_params()
    vocabulary = load_vocabulary(cfg.vocabulary) if cfg.vocabulary else None
    background = Worker(min_job_s=cfg.backend_throttle_ms / 1e3) if cfg.background else False
    slam = RgbdSlam(params, vocabulary=vocabulary, background=background,
                    defer_backend=cfg.live_backend_defer if cfg.live else 0,
                    backend_deferred_at=frozenset(int(s) for s in cfg.backend_deferred))
    if cfg.map:  # a saved map to track in (tracker/slam.py: SavedMapSearch); InputError when it cannot be read
        slam.adopt_map(load_map(cfg.map))
    return slam


def set_readout(odometry: Tracker, readout_s: float) -> None:
    """Give a tracker the camera's rolling-shutter readout before its first frame (a backend
    without a rolling-shutter model, ORB-SLAM3, has nothing to set)."""
    params = getattr(odometry, "params", None)
    if params is not None and hasattr(params, "readout_s"):
        odometry.params = dataclasses.replace(params, readout_s=float(readout_s))


def set_depth_model(odometry: Tracker, model: DepthModel | None) -> None:
    """Give a tracker the depth camera's error model before its first frame (tracker.config.
    with_depth_model); a tracker without one (ORB-SLAM3) or an unknown camera: nothing changes."""
    params = getattr(odometry, "params", None)
    if model is None or params is None or not hasattr(params, "depth"):
        return
    odometry.params = with_depth_model(params, model)
    odometry.depth_model = model
