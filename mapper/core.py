"""The mapper's core: keyframes → filtered dense cloud + occupancy octree, following pose corrections.

Keyframe poses arrive in the tracker's `world` (the first camera's optical frame); the cloud, the
octree and the grid are built in `map` (REP 105: z up, gravity-aligned when the source has an
accelerometer, see mapper.grid), so `map.bt` and `cloud.ply` stand upright in any viewer and the
octree's voxel columns are vertical. Each keyframe's filtered cloud is kept in its camera frame, so
a corrected pose, or a new `map` frame (`set_up`), only needs a new transform. The octree cannot
subtract one keyframe's contribution (log-odds are clamped), so a correction rebuilds it by
re-inserting keyframes in arrival order with the current poses, from a checkpoint of the octree
taken before the first keyframe that moved (every CHECKPOINT_EVERY keyframes, the newest
CHECKPOINTS kept): the files are, byte for byte, the map built from scratch with the final poses.
While the session runs, a keyframe moved by less than `mapper.move_tolerance_voxels` at every point
keeps its voxels where they went in (its dense cloud moves exactly), so the loop a live session
closes re-integrates only from the first keyframe it moved that far. The rebuild waits until the map
is looked at (a snapshot, the grid, the files): the loops closed between two snapshots cost one
rebuild, not one each, and keyframes that arrive meanwhile are inserted once, by it. What is looked
at is the same either way, so the outputs do not depend on when it ran.
"""

from __future__ import annotations

from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from octolog.kit.errors import InputError, MapError
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.mapper.cloud import DenseCloud, column_max, column_min, keyframe_cloud, rows_where, transform
from octolog.mapper.cloud import write_pcd, write_ply
from octolog.mapper.config import MapperConfig
from octolog.mapper.grid import OccupancyGrid2D, map_from_world_for_up, project_octree, write_map_server
from octolog.mapper.occupancy import OccupancyMap, make_occupancy_map
from octolog.mapper.params import GridParams, MapperParams
from octolog.mapper.tiles import Tiles
from octolog.mapper.voxelmap import Checkpoint, VoxelOccupancyMap

__all__ = ["FrameRef", "KeyframeCloud", "Mapper", "bt_payload", "make_mapper", "project_grid", "reaches",
           "write_map_files"]


@dataclass
class KeyframeCloud:
    """One integrated keyframe: its filtered cloud in the camera frame and its current pose."""

    points_cam: np.ndarray | None  # (N, 3) float64, filtered, camera frame (None: see `frame`)
    colours: np.ndarray | None  # (N, 3) uint8
    world_from_camera: np.ndarray  # 4x4
    stamp_ns: int
    seq: int
    stride: int = 0  # the pixel stride it was back-projected at (0: not recorded)
    inverse_offset: float = 0.0  # the depth correction its points took (Keyframe.depth_inverse_offset)
    # a shard keeps a keyframe that cannot reach its tiles as its frame, and makes its cloud only if a
    # correction brings it within reach: then as at arrival, with the depth re-corrections since
    frame: RgbdFrame | FrameRef | None = None
    recorrections: tuple[float, ...] = ()


# the octree's checkpoints (Mapper.rebuild): one every CHECKPOINT_EVERY keyframes inserted, the newest
# CHECKPOINTS kept (each a copy of the octree's voxels: a room's ~10 MB)
CHECKPOINT_EVERY = 10
CHECKPOINTS = 3


@dataclass(frozen=True)
class _Inserted:
    """Where a keyframe's scan went into the octree: its map pose, its depth correction, and the
    corners of the camera-frame box around its cloud and the camera (None: no cloud), which bound how
    far a new pose moves its points and rays (a rigid motion moves a box's points at most as far as
    one of its corners)."""

    map_from_camera: np.ndarray
    inverse_offset: float
    corners: np.ndarray | None

    def moved(self, map_from_camera: np.ndarray, inverse_offset: float, tolerance_m: float) -> bool:
        """Whether the keyframe now at `map_from_camera` moved any point farther than `tolerance_m`
        (0: at all) since, or took another depth correction."""
        if inverse_offset != self.inverse_offset:
            return True
        if tolerance_m <= 0 or self.corners is None:
            return not np.array_equal(map_from_camera, self.map_from_camera)
        d = self.corners @ (map_from_camera[:3, :3] - self.map_from_camera[:3, :3]).T + \
            (map_from_camera[:3, 3] - self.map_from_camera[:3, 3])
        return float(np.einsum("ij,ij->i", d, d).max()) > tolerance_m * tolerance_m


def _box_corners(points: np.ndarray | None) -> np.ndarray | None:
    if points is None or len(points) == 0:
        return None
    lo, hi = np.minimum(column_min(points), 0.0), np.maximum(column_max(points), 0.0)  # the camera's rays too
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


@dataclass
class FrameRef:
    """A keyframe's frame not at hand: what the map needs of it before its cloud (stamp, sequence
    number, camera, depth correction), and `load()` to fetch it when its cloud is made. A shard
    following a placement authority gets only the frames that reach its tiles (mapper/fleet/follow.py)."""

    stamp_ns: int
    seq: int
    intrinsics: Intrinsics
    depth_inverse_offset: float
    load: Callable[[], RgbdFrame]


def reaches(tiles: Tiles, map_from_camera: np.ndarray, intrinsics: Intrinsics, inverse_offset: float,
            max_range_m: float, resolution_m: float) -> bool:
    """Can a keyframe's points (and so its rays) reach `tiles`? Bounded by the camera position and
    the longest ray of the frustum at `max_range_m` after the depth correction, with a margin."""
    K = intrinsics
    corner = max(np.hypot(np.hypot((u - K.cx) / K.fx, (v - K.cy) / K.fy), 1.0)
                 for u in (0, K.width) for v in (0, K.height))
    longest = max_range_m / max(1e-3, 1.0 - max(0.0, inverse_offset) * max_range_m)
    reach = 1.1 * corner * longest + resolution_m
    centre = map_from_camera[:3, 3]
    return tiles.touches_box(centre[:2] - reach, centre[:2] + reach)


class Mapper:
    """Integrates keyframes; `correct` moves keyframes; `write` produces the map files."""

    def __init__(self, params: MapperParams) -> None:
        self.params = params
        self.keyframes: dict[int, KeyframeCloud] = {}  # insertion order = integration order
        self._cloud = DenseCloud(voxel_m=params.cloud.voxel_m)
        self._octree = self._new_octree()
        self._stale = False  # poses or the map frame moved since the octree and cloud were built
        self._inexact = False  # some keyframe's voxels lie where it was before a move within the tolerance
        self._inserted: dict[int, _Inserted] = {}  # the keyframes in the octree: the first n in arrival order
        self._checkpoints: list[tuple[int, Checkpoint]] = []  # (n keyframes inserted, the octree then)
        self.rebuilds = 0
        self.map_from_world = map_from_world(params.grid)  # 4x4: where the keyframes are put
        self.last_masked = np.zeros((0, 3))  # the last keyframe's movers: masked voxel centres, map frame
        self._version = 0  # counts changes to the octree, for `cloud_mask`'s cache
        self._mask: tuple[int, np.ndarray | None] | None = None

    def clear(self) -> None:
        """Forget every keyframe (the map frame and the parameters stay)."""
        self.keyframes = {}
        self._cloud = DenseCloud(voxel_m=self.params.cloud.voxel_m)
        self._octree = self._new_octree()
        self._stale = self._inexact = False
        self._inserted, self._checkpoints = {}, []
        self._version += 1

    def set_up(self, up: tuple[float, ...]) -> None:
        """A new up direction (in `world`) for the map frame; what is integrated moves into it."""
        grid = replace(self.params.grid, up=tuple(float(v) for v in up))
        self.params = replace(self.params, grid=grid)
        T = map_from_world(grid)
        if not np.array_equal(T, self.map_from_world):
            self.map_from_world = T
            if self.keyframes:
                self._stale = True

    @property
    def octree(self) -> OccupancyMap:
        """The occupancy map of every integrated keyframe at its current pose (rebuilt here when a
        correction or a new map frame left it stale, within `move_tolerance_m`)."""
        if self._stale:
            self.rebuild(self.params.move_tolerance_m)
        return self._octree

    @property
    def cloud(self) -> DenseCloud:
        """The dense cloud of every integrated keyframe at its current pose (as `octree`)."""
        if self._stale:
            self.rebuild(self.params.move_tolerance_m)
        return self._cloud

    @property
    def resolution_m(self) -> float:
        """The occupancy map's voxel size."""
        return self.params.occupancy.resolution_m

    def _new_octree(self) -> OccupancyMap:
        occ = self.params.occupancy
        return make_occupancy_map(occ.backend, occ.resolution_m, colour=occ.colour, model=occ.sensor,
                                  region=self.params.tiles, confirm_within=occ.confirm_within)

    def cloud_mask(self) -> np.ndarray | None:
        """Which points of the merged dense cloud (`cloud.cloud()`) the map keeps: with confirmed end
        points (`confirm_within`), those in occupied voxels, so what a person walking by or standing
        and leaving put in the keyframes goes with their voxels; None (all) when off."""
        octree = self.octree  # a pending correction first
        if not self.params.occupancy.confirm_within:
            return None
        if self._mask is None or self._mask[0] != self._version:
            self._mask = (self._version, octree.classify(self._cloud.cloud()[0]) == 1)
        return self._mask[1]

    def map_cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """The dense cloud as the map files hold it: merged, without what `cloud_mask` leaves out."""
        pts, cols = self.cloud.cloud()
        keep = self.cloud_mask()
        return (pts, cols) if keep is None else (pts[keep], cols[keep])

    def movers(self) -> dict[str, int]:
        """What was kept out as moving: unconfirmed end-point hits in voxels the map held free (over
        the whole build) and the dense cloud's points left out; {} when off."""
        keep = self.cloud_mask()
        if keep is None:
            return {}
        return {"masked_voxels": int(getattr(self.octree, "masked_total", 0)), "cleared_points": int((~keep).sum())}

    def _check_pose(self, kf_id: int, T: np.ndarray) -> None:
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(f"keyframe {kf_id}: pose is not a finite 4x4 transform")
        max_extent_m = self.params.max_extent_m
        if np.abs(T[:3, 3]).max() > max_extent_m:
            raise InputError(f"keyframe {kf_id}: camera at {np.round(T[:3, 3], 1).tolist()} m is outside the "
                             f"map bounds (±{max_extent_m:g} m)")

    def integrate(self, kf_id: int, world_from_camera: np.ndarray, frame: RgbdFrame | FrameRef) -> int:
        """Add one keyframe; returns its number of filtered points. Bad keyframes raise InputError
        before anything is changed."""
        self._check_pose(kf_id, world_from_camera)
        if kf_id in self.keyframes:
            raise InputError(f"keyframe {kf_id}: already integrated")
        if not isinstance(frame, FrameRef) and not np.any(frame.depth):  # a FrameRef's was checked where it is
            raise InputError(f"keyframe {kf_id}: no valid depth")
        stride = self._stride(frame.stamp_ns)
        kf = KeyframeCloud(None, None, world_from_camera.copy(), frame.stamp_ns, frame.seq, stride,
                           frame.depth_inverse_offset, frame=frame)
        if self._within_reach(kf) and self._make_cloud(kf) == 0:
            raise InputError(f"keyframe {kf_id}: no valid depth within {self.params.cloud.max_range_m} m")
        self.keyframes[kf_id] = kf
        if not self._stale:  # else the coming rebuild inserts it
            self._insert(kf_id, kf)
        return 0 if kf.points_cam is None else len(kf.points_cam)

    def _make_cloud(self, kf: KeyframeCloud) -> int:
        """The keyframe's filtered camera-frame cloud from its frame (then dropped); its size."""
        c, frame = self.params.cloud, kf.frame
        if isinstance(frame, FrameRef):
            frame = frame.load()
        assert frame is not None
        pts, cols = keyframe_cloud(
            frame.depth, frame.rgb, frame.intrinsics, frame.depth_scale_m, np.eye(4),
            max_range_m=c.max_range_m, stride=kf.stride, nb_neighbors=c.sor_neighbors,
            std_ratio=c.sor_std_ratio, voxel_m=c.voxel_m, sor_first=c.sor_first, outliers=c.outliers,
            inverse_offset=frame.depth_inverse_offset)
        for delta in kf.recorrections:
            pts = pts / (1.0 - delta * pts[:, 2:3])
        kf.points_cam, kf.colours, kf.frame, kf.recorrections = pts, cols, None, ()
        return len(pts)

    def _within_reach(self, kf: KeyframeCloud) -> bool:
        """Can the keyframe's points (and so its rays) reach this map's tiles at its current pose?
        Always, for a whole map. A shard bounds them by the camera position and the longest ray of
        the frustum at `max_range_m` after the depth correction, with a margin."""
        tiles = self.params.tiles
        if tiles is None or kf.frame is None:
            return True
        return reaches(tiles, self.map_from_world @ kf.world_from_camera, kf.frame.intrinsics, kf.inverse_offset,
                       self.params.cloud.max_range_m, self.resolution_m)

    def _stride(self, stamp_ns: int) -> int:
        """The pixel stride for a keyframe taken at `stamp_ns`: `cloud.pixel_stride`, or
        `cloud.burst_stride` once `cloud.full_per_s` keyframes at full stride were integrated in
        the second of camera time before it. A fast turn makes a burst of keyframes of mostly the
        same surfaces; each costs the mapper its pixels and their rays, and the two cores are the
        tracker's too. Decided by sensor time alone, so a replay makes the same map."""
        c = self.params.cloud
        if c.full_per_s <= 0:
            return c.pixel_stride
        recent = sum(1 for kf in self.keyframes.values()
                     if kf.stride == c.pixel_stride and 0 <= stamp_ns - kf.stamp_ns < 1_000_000_000)
        return c.pixel_stride if recent < c.full_per_s else max(c.pixel_stride, c.burst_stride)

    def _insert(self, kf_id: int, kf: KeyframeCloud) -> None:
        if (scan := self._place(kf_id, kf)) is None:
            if isinstance(self._octree, VoxelOccupancyMap):
                self._octree.elsewhere()  # a shard: still one of the scans that confirm end points
        else:
            pts, origin, colours = scan
            # the range limit was applied when back-projecting (depth <= max_range_m), so the dense
            # cloud and the octree hold the same points; a second, Euclidean cut would make them differ
            self._octree.insert(pts, origin, colours=colours, max_range_m=-1.0)
            self._version += 1
            if isinstance(self._octree, VoxelOccupancyMap):
                self.last_masked = self._octree.masked_centres()
        self._inserted_now(kf_id, kf)

    def _inserted_now(self, kf_id: int, kf: KeyframeCloud) -> None:
        """Keyframe `kf_id` (the next in arrival order) just went into the octree; a checkpoint when due."""
        self._inserted[kf_id] = _Inserted(self.map_from_world @ kf.world_from_camera, kf.inverse_offset,
                                          _box_corners(kf.points_cam))
        n = len(self._inserted)
        if n % CHECKPOINT_EVERY == 0 and isinstance(self._octree, VoxelOccupancyMap):
            self._checkpoints = [*self._checkpoints, (n, self._octree.checkpoint())][-CHECKPOINTS:]

    def _place(self, kf_id: int, kf: KeyframeCloud) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
        """The keyframe's points into the dense cloud at its current pose; its scan for the octree
        (map-frame points, camera origin, colours or None), None when it reaches none of the map."""
        if kf.points_cam is None:
            if not self._within_reach(kf):
                self._cloud.remove(kf_id)
                return None
            self._make_cloud(kf)
        map_from_camera = self.map_from_world @ kf.world_from_camera
        pts = transform(kf.points_cam, map_from_camera)
        tiles = self.params.tiles
        if tiles is None:
            self._cloud.add(kf_id, pts, kf.colours)
        else:  # a shard: the cloud's points in its tiles; the octree keeps its tiles' voxels itself
            mine = tiles.keep_points(pts)
            self._cloud.add(kf_id, rows_where(pts, mine), rows_where(kf.colours, mine))
        return pts, map_from_camera[:3, 3], kf.colours if self.params.occupancy.colour else None

    def correct(self, poses: dict[int, np.ndarray], depth_inverse_offset: float | None = None) -> int:
        """Move known keyframes to corrected poses, and with `depth_inverse_offset` (the tracker's new
        depth correction, KeyframePoses) re-correct their depth; returns how many changed (unknown ids
        are ignored)."""
        moved = {i: T for i, T in poses.items() if i in self.keyframes
                 and not np.array_equal(T, self.keyframes[i].world_from_camera)}
        for i, T in moved.items():
            self._check_pose(i, T)
        changed = set(moved)
        if depth_inverse_offset is not None:
            changed |= self.recorrect_depth([i for i in poses if i in self.keyframes], depth_inverse_offset)
        for i, T in moved.items():
            self.keyframes[i].world_from_camera = T.copy()
        if changed:
            self._stale = True  # rebuilt when next looked at
        return len(changed)

    def recorrect_depth(self, ids: list[int], inverse_offset: float) -> set[int]:
        """Give keyframes `ids` the depth correction `inverse_offset` (1/m: 1/z <- 1/z - offset) in
        place of the one they were integrated with: each point moves along its ray. Returns the ids
        that changed; the map is rebuilt when next looked at."""
        changed = set()
        for i in ids:
            kf = self.keyframes[i]
            delta = inverse_offset - kf.inverse_offset
            if delta and kf.points_cam is None:
                kf.recorrections += (delta,)
                kf.inverse_offset = inverse_offset
                changed.add(i)
            elif delta:
                kf.points_cam = kf.points_cam / (1.0 - delta * kf.points_cam[:, 2:3])
                kf.inverse_offset = inverse_offset
                changed.add(i)
        if changed:
            self._stale = True
        return changed

    def rebuild(self, tolerance_m: float = 0.0, merge_on: Executor | None = None) -> None:
        """Bring the map to the keyframes' current poses (and map frame): every keyframe's cloud placed
        anew, and the octree re-integrated, in arrival order, from the newest checkpoint before the
        first keyframe that moved more than `tolerance_m` at any point (0: at all) or arrived since;
        nothing when none did. With `merge_on` (a whole map), the clouds are placed first and the dense
        cloud merged on that executor while the octree is rebuilt from the placed points: the merge
        needs no octree, and at a run's end it would otherwise follow the rebuild. The same map either way."""
        ids = list(self.keyframes)
        current = {k: (self.map_from_world @ kf.world_from_camera, kf.inverse_offset) for k, kf in self.keyframes.items()}

        def moved(k: int, tol: float) -> bool:
            return k not in self._inserted or self._inserted[k].moved(*current[k], tol)

        start = next((i for i, k in enumerate(ids) if moved(k, tolerance_m)), len(ids))
        self._inexact = tolerance_m > 0 and any(moved(k, 0.0) for k in ids[:start])
        at = len(ids)
        if start < len(ids):
            at, checkpoint = max(((n, c) for n, c in self._checkpoints if n <= start), default=(0, None),
                                 key=lambda nc: nc[0])
            self._checkpoints = [(n, c) for n, c in self._checkpoints if n <= at]
            for k in ids[at:]:
                self._inserted.pop(k, None)
            if checkpoint is None:
                self._octree = self._new_octree()
            else:
                self._octree.restore(checkpoint)
        self._stale = False
        self._version += 1
        if merge_on is not None and self.params.tiles is None:
            for kf_id, kf in self.keyframes.items():
                self._place(kf_id, kf)  # its points stay in the cloud, where the octree's scans read them
            merge_on.submit(self._cloud.cloud)
            colour = self.params.occupancy.colour
            scans = ((self._cloud.points_of(k), current[k][0][:3, 3], self.keyframes[k].colours if colour else None)
                     for k in ids[at:])
        else:
            for k in ids[:at]:
                self._place(k, self.keyframes[k])
            scans = (self._place(k, self.keyframes[k]) for k in ids[at:])
        if at == len(ids):
            return
        pending = iter(ids[at:])

        def committed() -> None:
            k = next(pending)
            self._inserted_now(k, self.keyframes[k])

        if isinstance(self._octree, VoxelOccupancyMap):  # the next keyframe's rays cast while one goes in
            self._octree.insert_all(scans, max_range_m=-1.0, committed=committed)
        else:
            for scan in scans:
                if scan is not None:
                    pts, origin, colours = scan
                    self._octree.insert(pts, origin, colours=colours, max_range_m=-1.0)
                committed()
        self.rebuilds += 1

    def stats(self) -> dict:
        """The occupancy map's counts plus keyframes and rebuilds, the frame the map is in
        (`map_from_world`, row-major 4x4: where the tracker's poses land) and the depth corrections
        its keyframes took (1/m, each distinct value once), for map_stats.json."""
        offsets = sorted({kf.inverse_offset for kf in self.keyframes.values()})
        movers = self.movers()
        return {**self.octree.stats(), "keyframes": len(self.keyframes), "rebuilds": self.rebuilds,
                "map_from_world": self.map_from_world.tolist(), "depth_inverse_offsets": offsets,
                **({"movers": movers} if movers else {})}

    def project_grid(self) -> OccupancyGrid2D | None:
        """The 2D grid of the current octree, or None while no known voxel lies in the band."""
        return project_grid(self.octree, self.params.grid, self.map_from_world)

    def write(self, out_dir: Path, stem: str = "map", *, meanwhile: Callable[[], None] | None = None) -> dict[str, str]:
        """Write the map files (.bt, .ot, cloud .ply/.pcd, the 2D grid if any); returns {kind: path}.

        The dense cloud is merged and written on a second thread while the octree's files are written
        and `meanwhile` runs (the run's last snapshot): the merge's compiled kernels and NumPy run
        without the GIL, so at a run's end, the tracker gone, the mapper has both cores. The files
        are the same bytes either way."""
        out_dir.mkdir(parents=True, exist_ok=True)
        with ThreadPoolExecutor(1, thread_name_prefix="mapper-cloud") as pool:
            if self._stale or self._inexact:  # the exact map of the final poses: the cloud merges meanwhile
                self.rebuild(merge_on=pool)
            octree = self.octree
            cloud = pool.submit(lambda: _cloud_files(out_dir, *self.map_cloud()))  # after the merge: one thread
            if meanwhile is not None:
                meanwhile()
            files = _octree_files(out_dir, octree, stem)
            grid = _grid_files(out_dir, self.project_grid(), stem)
            return {**files, **cloud.result(), **grid}


def write_map_files(out_dir: Path, octree: OccupancyMap, points: np.ndarray, colours: np.ndarray,
                    grid: OccupancyGrid2D | None, stem: str = "map") -> dict[str, str]:
    """The map files of an octree, a dense cloud and a grid (None: no grid files); {kind: path}."""
    out_dir.mkdir(parents=True, exist_ok=True)
    return {**_octree_files(out_dir, octree, stem), **_cloud_files(out_dir, points, colours),
            **_grid_files(out_dir, grid, stem)}


def _octree_files(out_dir: Path, octree: OccupancyMap, stem: str) -> dict[str, str]:
    bt, ot = out_dir / f"{stem}.bt", out_dir / f"{stem}.ot"
    octree.write_bt(bt)
    octree.write_ot(ot)
    return {"bt": str(bt), "ot": str(ot)}


def _cloud_files(out_dir: Path, points: np.ndarray, colours: np.ndarray) -> dict[str, str]:
    ply, pcd = out_dir / "cloud.ply", out_dir / "cloud.pcd"
    write_ply(ply, points, colours)
    write_pcd(pcd, points, colours)
    return {"ply": str(ply), "pcd": str(pcd)}


def _grid_files(out_dir: Path, grid: OccupancyGrid2D | None, stem: str) -> dict[str, str]:
    if grid is None:
        return {}
    return {f"grid_{k}": v for k, v in write_map_server(grid, out_dir / stem).items()}


def make_mapper(cfg: MapperConfig) -> Mapper:
    """A `Mapper` from the `[mapper]` config (validated once, here, through `cfg.params()`)."""
    return Mapper(cfg.params())


def map_from_world(params: GridParams) -> np.ndarray:
    """The map frame (z up, see mapper.grid) the grid lies in, from the world frame."""
    return map_from_world_for_up(np.array(params.up, dtype=float), height_m=params.camera_height_m)


def project_grid(octree: OccupancyMap, params: GridParams, map_from_world: np.ndarray) -> OccupancyGrid2D | None:
    """The 2D occupancy grid of `octree` (built in `map`): its height band, or None while no known
    voxel lies in the band. The grid keeps `map_from_world`, to place world points in it."""
    try:
        grid = project_octree(octree, map_from_world=np.eye(4), z_min_m=params.z_min_m,
                              z_max_m=params.z_max_m, resolution_m=params.resolution_m)
    except MapError:
        return None
    return replace(grid, map_from_world=map_from_world.copy())


def bt_payload(bt_file_bytes: bytes) -> bytes:
    """The data part of a .bt file (what octomap_msgs/Octomap carries): everything after `data\\n`."""
    marker = b"\ndata\n"
    at = bt_file_bytes.find(marker)
    if at < 0:
        raise InputError("not an OctoMap binary (.bt) stream: no 'data' line")
    return bt_file_bytes[at + len(marker):]
