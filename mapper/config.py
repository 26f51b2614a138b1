"""Mapper settings: the `[mapper]` config section, its one validator, and the core's parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from octolog.kit.errors import ConfigError
from octolog.mapper.fleet.order import start_pose_matrix
from octolog.mapper.params import BACKENDS, DEFAULT_UP, CloudParams, GridParams, MapperParams, OccupancyParams
from octolog.mapper.sensor_model import PROBABILITIES, SensorModel
from octolog.mapper.tiles import Tiles, parse_shard

_OCTOMAP = SensorModel()  # OctoMap's defaults


@dataclass(frozen=True)
class MapperConfig:
    """The mapper process's settings (`--set mapper.KEY=V`); documented in docs/cli.md."""

    resolution_m: float = 0.05  # occupancy octree leaf size
    # "numpy": our vectorised occupancy map (same states and files as OctoMap, 1.4-3x faster);
    # "octomap": OctoMap itself through pyoctomap, the reference
    backend: str = "numpy"
    colour: bool = True  # colour per occupied voxel (map.ot is a ColorOcTree)
    # OctoMap's sensor model (mapper/sensor_model.py): the probability an end point / a ray's voxel
    # is occupied, the clamping of the log-odds, and the occupancy threshold; OctoMap's defaults but
    # clamp_max: 0.9, not 0.97, so where a person stood for five seconds six rays through it clear the
    # voxel, not nine (people walking through: docs/architecture.md)
    prob_hit: float = _OCTOMAP.prob_hit
    prob_miss: float = _OCTOMAP.prob_miss
    clamp_min: float = _OCTOMAP.clamp_min
    clamp_max: float = 0.9
    occupancy_thres: float = _OCTOMAP.occupancy_thres
    # people walking through (mapper/voxelmap.py): an end point counts in the octree once one of the
    # confirm_within keyframes before it hit the same voxel too (or the voxel is occupied already);
    # its ray clears space either way. The files' dense cloud keeps the points in occupied voxels.
    # 0: every end point counts at once (OctoMap). The numpy backend only.
    confirm_within: int = 2
    voxel_m: float = 0.01  # dense cloud voxel filter (second layer)
    max_range_m: float = 4.0  # depth readings beyond this are ignored
    pixel_stride: int = 2  # back-project every n-th pixel in each direction
    # at most this many keyframes in a second of camera time at `pixel_stride`; the rest of a burst
    # (a fast turn: one every 3-5 frames) at `burst_pixel_stride`, a quarter of the points and rays
    # at 4, so a burst cannot starve the tracker of the cores it shares (0: no limit)
    full_keyframes_per_s: float = 4.0
    burst_pixel_stride: int = 4
    sor_neighbors: int = 20  # statistical outlier removal (first layer)
    # 3 sigma, not PCL's usual 2: a per-keyframe threshold at 2 sigma drops 15-50 % of floor and
    # ceiling points seen at grazing angles (synthetic room: 96.2 % of observed surface voxels occupied
    # at 2 sigma, 99.1 % at 3 sigma; docs/results.md)
    sor_std_ratio: float = 3.0
    # the first filter layer: "image" (default): each point against its 5x5 pixel neighbourhood, in units
    # of its pixel footprint (2-5x cheaper than a k-d tree; mapper/cloud.py: image_outlier_removal);
    # "knn": PCL's statistical outlier removal over the `sor_neighbors` nearest points in 3D (the paper's)
    outliers: str = "image"
    # outliers="knn" only; false: 1 cm voxel grid before the outlier filter (3x faster, same result on
    # real data); true: the paper's order, outlier filter on the raw back-projected points first
    sor_first: bool = False
    # publish the map (octomap, occupied voxels, 2D grid) every n keyframes and at the end; 0: end only.
    # Counted in keyframes, not seconds, so the session log stays deterministic.
    publish_every: int = 10
    # while the session runs, a correction re-integrates the octree from the first keyframe it moved
    # by more than this many voxels at any of its points (the others keep their voxels where they went
    # in; every dense-cloud point moves exactly): below a quarter voxel a keyframe's voxels barely
    # change, and the loop a live session closes costs no rebuild of the whole map. The files are the
    # exact map of the final poses whatever this is. 0: every snapshot exact too.
    move_tolerance_voxels: float = 0.25
    # an earlier session's folder whose map this one starts from and extends (mapper/prior.py; `octolog
    # run --map` sets it, with that session's grid_up); "": an empty map
    prior: str = ""
    # cameras farther than this from the origin are refused (OctoMap's 5 cm key range is ±1638 m)
    max_extent_m: float = 1000.0
    # 2D occupancy grid: the band of heights projected, in a level frame whose +z is `grid_up`
    # (world = first camera frame; (0, -1, 0) is up for a camera held level at start), with
    # z = 0 at the floor if `grid_camera_height_m` gives the first camera's height, else at the camera
    # (empty: `octolog run` takes it from the source's accelerometer, else (0, -1, 0), a level camera)
    grid_up: tuple[float, ...] = ()
    grid_camera_height_m: float = 0.0
    grid_z_min_m: float = -1.0
    grid_z_max_m: float = 0.3
    grid_resolution_m: float = 0.05
    wait_for: tuple[str, ...] = ()  # stages that must be up before the mapper starts listening
    wait_timeout_s: float = 60.0  # how long to wait for them
    # several robots into one map: the robots' namespaces (each a replay/recorder + tracker pair);
    # empty: one robot, in the mapper's own namespace. See mapper/fleet/order.py for the integration order.
    robots: tuple[str, ...] = ()
    # per robot, its start frame (its tracker's world) in the common world: x y z qx qy qz qw;
    # empty: every robot starts at the world origin
    start_poses: tuple[tuple[float, ...], ...] = ()
    # a robot silent this long (alive: its tracker answers) no longer holds the others back; its later
    # keyframes come late and the map is built again in the defined order at the end. 0: wait for it
    robot_stall_s: float = 30.0
    # placed without start poses: a robot's keyframe once it has come this far (metres of its own
    # path) since its last link is matched against the other robots' nearest map keyframes (robots
    # that meet again are linked again, the joint graph settles them; mapper/fleet/placement.py). The
    # default: at the joint graph's 1 % drift, 2 m make ~2 cm, as much as a link's own error; a link
    # sooner would weigh its error against a robot's better own path. 0: links only while placing
    relink_after_m: float = 2.0
    # one shard of a map split across mapper processes (mapper/tiles.py): "K/N" keeps the voxels of
    # the tiles shard K of N owns, `octolog stitch` joins the shards' folders into the whole map;
    # "": the whole map. Tiles are `tile_m` squares on the map's floor; a keyframe reaches ~13 m across
    # (4 m of depth at a D455's field of view), so tiles larger than that spare a shard most of the
    # keyframes of its neighbours' tiles
    shard: str = ""
    tile_m: float = 16.0
    # a sharded fleet map has one placement authority: the shard without `follow` places the robots
    # and publishes every call it makes on its map (stage `placement` in its namespace; its folder's
    # placed.jsonl, mapper/fleet/journal.py). `follow` names it: its namespace (live), or
    # "journal:PATH" (its folder or placed.jsonl) to build this shard again from the robots' logs.
    # "": this mapper places the robots itself
    follow: str = ""

    def validate(self) -> None:
        """The one check of every value; the core and the backends trust what passes it."""
        for key in ("resolution_m", "voxel_m", "max_range_m", "max_extent_m", "grid_resolution_m"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"mapper.{key} {getattr(self, key)}: want > 0")
        if self.grid_up and (len(self.grid_up) != 3 or not any(self.grid_up)):
            raise ConfigError(f"mapper.grid_up {self.grid_up}: want a non-zero 3-vector (or [] for the source's IMU)")
        if not self.grid_z_min_m < self.grid_z_max_m:
            raise ConfigError(f"mapper.grid_z_min_m {self.grid_z_min_m} must be below grid_z_max_m {self.grid_z_max_m}")
        if self.backend not in BACKENDS:
            raise ConfigError(f"mapper.backend {self.backend!r}: want numpy or octomap")
        if not (math.isfinite(self.move_tolerance_voxels) and self.move_tolerance_voxels >= 0):
            raise ConfigError(f"mapper.move_tolerance_voxels {self.move_tolerance_voxels}: want a number >= 0")
        if self.confirm_within < 0:
            raise ConfigError(f"mapper.confirm_within {self.confirm_within}: want >= 0 (0: off)")
        if not (math.isfinite(self.robot_stall_s) and self.robot_stall_s >= 0):
            raise ConfigError(f"mapper.robot_stall_s {self.robot_stall_s}: want >= 0 (0: wait for every robot)")
        if self.follow and not self.robots:
            raise ConfigError(f"mapper.follow {self.follow!r}: only for a fleet map (mapper.robots)")
        if not (math.isfinite(self.relink_after_m) and self.relink_after_m >= 0):
            raise ConfigError(f"mapper.relink_after_m {self.relink_after_m}: want >= 0 (0: off)")
        if self.publish_every < 0:
            raise ConfigError(f"mapper.publish_every {self.publish_every}: want >= 0")
        if self.pixel_stride < 1:
            raise ConfigError(f"mapper.pixel_stride {self.pixel_stride}: want >= 1")
        if self.burst_pixel_stride < 1:
            raise ConfigError(f"mapper.burst_pixel_stride {self.burst_pixel_stride}: want >= 1")
        if not (math.isfinite(self.full_keyframes_per_s) and self.full_keyframes_per_s >= 0):
            raise ConfigError(f"mapper.full_keyframes_per_s {self.full_keyframes_per_s}: want >= 0 (0: no limit)")
        if self.outliers not in ("image", "knn"):
            raise ConfigError(f"mapper.outliers {self.outliers!r}: want image or knn")
        if self.sor_neighbors < 1:
            raise ConfigError(f"mapper.sor_neighbors {self.sor_neighbors}: want >= 1")
        if not math.isfinite(self.sor_std_ratio):
            raise ConfigError(f"mapper.sor_std_ratio {self.sor_std_ratio}: want a finite number")
        wrong = self.sensor_model().problem()
        if wrong is not None:
            what, why = wrong
            raise ConfigError(f"mapper.{what} {why}" if what in PROBABILITIES else f"mapper {what} {why}")
        self.tiles()
        for robot in self.robots:
            if not robot.strip("/") or any(c in robot for c in "*$?#"):
                raise ConfigError(f"mapper.robots {robot!r}: want a Zenoh key prefix such as robot1")
        if len(set(self.robots)) != len(self.robots):
            raise ConfigError(f"mapper.robots {list(self.robots)}: a namespace is listed twice")
        if self.start_poses and len(self.start_poses) != len(self.robots):
            raise ConfigError(f"mapper.start_poses: {len(self.start_poses)} poses for {len(self.robots)} robots "
                              f"(want one x y z qx qy qz qw per robot, or none)")
        for robot, pose in zip(self.robots, self.start_poses):
            start_pose_matrix(robot, pose)

    def sensor_model(self) -> SensorModel:
        """OctoMap's sensor model from the `prob_*`, `clamp_*` and `occupancy_thres` keys."""
        return SensorModel(prob_hit=self.prob_hit, prob_miss=self.prob_miss, clamp_min=self.clamp_min,
                           clamp_max=self.clamp_max, occupancy_thres=self.occupancy_thres)

    def params(self) -> MapperParams:
        """The core's parameter object (`Mapper` takes it whole), from a validated config."""
        self.validate()
        return MapperParams(
            cloud=CloudParams(max_range_m=self.max_range_m, pixel_stride=self.pixel_stride, voxel_m=self.voxel_m,
                              sor_neighbors=self.sor_neighbors, sor_std_ratio=self.sor_std_ratio,
                              sor_first=self.sor_first, outliers=self.outliers,
                              full_per_s=self.full_keyframes_per_s, burst_stride=self.burst_pixel_stride),
            occupancy=OccupancyParams(backend=self.backend, resolution_m=self.resolution_m, colour=self.colour,
                                      sensor=self.sensor_model(),
                                      # a fleet's keyframes come in turn, one robot's after another's
                                      confirm_within=(self.confirm_within * max(1, len(self.robots))
                                                      if self.backend == "numpy" else 0)),
            grid=GridParams(up=self.grid_up or DEFAULT_UP, camera_height_m=self.grid_camera_height_m, z_min_m=self.grid_z_min_m,
                            z_max_m=self.grid_z_max_m, resolution_m=self.grid_resolution_m),
            max_extent_m=self.max_extent_m,
            tiles=self.tiles(),
            move_tolerance_m=self.move_tolerance_voxels * self.resolution_m,
        )

    @property
    def stage(self) -> str:
        """The name the mapper announces itself by on the bus: "mapper", or "mapper-K" for shard K
        (each shard is a stage of its own; a replay waits for every shard by name)."""
        return f"mapper-{parse_shard(self.shard)[0]}" if self.shard else "mapper"

    def tiles(self) -> Tiles | None:
        """This shard's tiles (`shard` K/N), or None for the whole map."""
        if not self.shard:
            return None
        k, n = parse_shard(self.shard)
        if self.backend != "numpy":
            raise ConfigError(f"mapper.shard {self.shard!r} needs mapper.backend = \"numpy\"")
        if not (math.isfinite(self.tile_m) and self.tile_m > 0):
            raise ConfigError(f"mapper.tile_m {self.tile_m}: want > 0")
        return Tiles(k, n, float(self.tile_m), self.resolution_m, self.voxel_m)

    def start_pose_matrices(self) -> list[np.ndarray]:
        """world_from_<robot> for each robot (identity when no start poses are given)."""
        if not self.start_poses:
            return [np.eye(4) for _ in self.robots]
        return [start_pose_matrix(r, p) for r, p in zip(self.robots, self.start_poses)]
