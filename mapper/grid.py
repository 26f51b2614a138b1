"""The 2D occupancy grid a robot navigates with, projected from the 3D occupancy map.

Frames. The tracker's world frame is its first camera's optical frame (x right, y down, z forward):
not gravity-aligned, and its origin is the first camera centre, not the floor. The grid lives in a
*map* frame whose +z is "up": `map_from_world_for_up` builds it from the up direction expressed in
world coordinates (for a camera held level at start, up = (0, -1, 0)). The map's x axis is the
world's +z (the first camera's viewing direction) projected onto the horizontal plane, so the map
is x forward, y left, z up (REP 103), and map z = 0 is at the first camera's height unless
`height_m` says how far above the floor that camera was.

Grid. Cell (row r, column c) covers map x in [origin_x + c*res, origin_x + (c+1)*res) and map y in
[origin_y + r*res, origin_y + (r+1)*res): row 0 is the lowest y, as in nav_msgs/OccupancyGrid
(`data` row-major from cell (0, 0) at the lower-left). Cell edges lie on multiples of the
resolution in the map frame, so grids of the same map at the same resolution always line up.
Values follow nav_msgs: -1 unknown, 0 free, 100 occupied.

Files. `write_map_server` writes what ROS `map_server` / `nav2_map_server` load (and `map_saver`
writes): a binary PGM (P5, 8 bit, occupied 0, free 254, unknown 205, first image row = highest y)
and a YAML file (image, mode trinary, resolution, origin [x, y, yaw], negate 0, occupied_thresh
0.65, free_thresh 0.196). With these thresholds map_server reads 205 back as unknown
(p = (255 - 205) / 255 = 0.19608 is not < 0.196) and 254 as free, 0 as occupied, so a saved
grid loads back unchanged. Everything here is deterministic: same input, same bytes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from octolog.kit.errors import MapError
from octolog.kit.files import write_bytes_atomic
from octolog.mapper.cloud import column_max, column_min, rows_where
from octolog.mapper.params import DEFAULT_UP
from octolog.schemas import codec
from octolog.schemas.msgtypes import OccupancyGrid

__all__ = [
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "OccupancyGrid2D",
    "grid_from_msg",
    "map_from_world_for_up",
    "occupancy_grid_msg",
    "pgm_bytes",
    "project_grid",
    "project_octree",
    "write_map_server",
    "yaml_text",
]

UNKNOWN, FREE, OCCUPIED = -1, 0, 100
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
_MIN_HORIZONTAL = 1e-3  # below this, world +z is treated as vertical and world +x gives the heading


class VoxelCentres(Protocol):
    """An occupancy map as far as its voxel centres go: what the grid projection and mapper.evaluate read
    (mapper.occupancy.OccupancyMap has it; not imported here: it loads both backends, and mapper.config
    imports this module)."""

    resolution: float

    def occupied_centres(self, max_voxels: int | None = None) -> np.ndarray: ...

    def free_centres(self, max_voxels: int | None = None) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class OccupancyGrid2D:
    """A 2D occupancy grid in the map frame.

    `data[r, c]` (int8: -1 unknown, 0 free, 100 occupied) is the cell whose lower-left corner is at
    map (origin_x + c * res, origin_y + r * res); row 0 is the lowest y. `map_from_world` (4x4) is
    the transform from the mapper's world frame into the map frame the grid lies in.
    """

    data: np.ndarray
    resolution_m: float
    origin_xy: tuple[float, float]
    map_from_world: np.ndarray

    @property
    def height(self) -> int:
        """Rows (cells along map y)."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Columns (cells along map x)."""
        return int(self.data.shape[1])

    def cell_of(self, xy_map: np.ndarray) -> np.ndarray:
        """(row, col) int64 indices (N, 2) of map-frame points (N, 2); may fall outside the grid."""
        xy = np.asarray(xy_map, dtype=np.float64).reshape(-1, 2)
        ox, oy = self.origin_xy
        col = np.floor((xy[:, 0] - ox) / self.resolution_m).astype(np.int64)
        row = np.floor((xy[:, 1] - oy) / self.resolution_m).astype(np.int64)
        return np.stack([row, col], axis=1)


# ---- frames -------------------------------------------------------------------------------------


def map_from_world_for_up(up_world: np.ndarray | tuple[float, float, float] = DEFAULT_UP, *,
                          height_m: float = 0.0) -> np.ndarray:
    """A 4x4 map_from_world whose +z is `up_world` (any length), x forward, y left.

    Map x is the world's +z axis (the first camera's viewing direction) projected onto the plane
    normal to up; if world +z is (within ~0.06 deg) vertical, world +x projected is used instead.
    y = z cross x makes the frame right-handed. The map origin lies `height_m` below the world
    origin along up, so map z is the height above the floor when `height_m` is the first camera's
    height (0 keeps map z = 0 at the first camera). Deterministic: same input, same matrix.
    For the default up (0, -1, 0): map x = world z, map y = -world x, map z = -world y.
    """
    up = np.asarray(up_world, dtype=np.float64).reshape(-1)
    if up.shape != (3,) or not np.isfinite(up).all():
        raise MapError(f"up must be a finite 3-vector, got {up_world!r}")
    norm = float(np.linalg.norm(up))
    if norm < 1e-9:
        raise MapError("up must be a non-zero vector")
    if not np.isfinite(height_m):
        raise MapError(f"height_m must be finite, got {height_m}")
    z = up / norm
    x = None
    for axis in (np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])):
        h = axis - (axis @ z) * z
        n = float(np.linalg.norm(h))
        if n >= _MIN_HORIZONTAL:
            x = h / n
            break
    assert x is not None  # world z and x cannot both be parallel to up
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])  # rows: map axes in world coordinates
    T[2, 3] = float(height_m)
    return T


def _check_transform(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise MapError(f"map_from_world must be a finite 4x4 transform, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise MapError("map_from_world must be a rigid transform (rotation + translation)")
    return T


# ---- projection ---------------------------------------------------------------------------------


def _centres(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.size == 0:
        return np.zeros((0, 3), dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MapError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise MapError(f"{name} contain NaN or infinite coordinates")
    return p


def project_grid(
    occupied_centres: np.ndarray,
    free_centres: np.ndarray,
    *,
    resolution_m: float,
    map_from_world: np.ndarray,
    z_min_m: float,
    z_max_m: float,
    padding_cells: int = 2,
) -> OccupancyGrid2D:
    """Project voxel centres (world frame) in the height band onto a 2D grid.

    A voxel is in the band if its centre's map z is in [z_min_m, z_max_m]. A cell is occupied (100)
    if an occupied voxel in the band projects into it, free (0) if a free one does and no occupied
    one does, unknown (-1) otherwise. The grid spans the band's voxels plus `padding_cells` unknown
    cells on every side. Voxel centres are projected, not footprints: with a grid as fine as the
    voxels and a map frame rotated against the voxel axes, thin walls can alias (gaps between
    cells); a grid resolution >= the voxel size avoids that. Raises MapError if no voxel is in the band.
    """
    if not (np.isfinite(resolution_m) and resolution_m > 0):
        raise MapError(f"grid resolution must be a positive number, got {resolution_m}")
    if not (np.isfinite(z_min_m) and np.isfinite(z_max_m) and z_min_m <= z_max_m):
        raise MapError(f"height band must be finite with z_min <= z_max, got [{z_min_m}, {z_max_m}]")
    if not isinstance(padding_cells, (int, np.integer)) or padding_cells < 0:
        raise MapError(f"padding_cells must be a non-negative integer, got {padding_cells!r}")
    T = _check_transform(map_from_world)
    occ = _centres(occupied_centres, "occupied centres")
    free = _centres(free_centres, "free centres")
    R, t = T[:3, :3], T[:3, 3]

    identity = np.array_equal(T, np.eye(4))  # the product with I gives the same numbers: skipped

    def band_keys(p: np.ndarray) -> np.ndarray:
        m = p if identity else p @ R.T + t
        z = m[:, 2]
        band = (z >= z_min_m) & (z <= z_max_m)
        if not band.all():
            m = rows_where(m, band)
        keys = np.empty((m.shape[0], 2), dtype=np.int64)  # (N, 2) cell keys (x, y), a column at a time
        for j in range(2):
            keys[:, j] = np.floor(m[:, j] / resolution_m)
        return keys

    k_occ, k_free = band_keys(occ), band_keys(free)
    parts = [k for k in (k_occ, k_free) if k.shape[0]]
    if not parts:
        raise MapError(f"no voxels between z = {z_min_m:g} and {z_max_m:g} m in the map frame")
    lo = np.min([column_min(k) for k in parts], axis=0) - int(padding_cells)
    hi = np.max([column_max(k) for k in parts], axis=0) + int(padding_cells)
    width, height = (hi - lo + 1).tolist()
    if width * height > 100_000_000:
        raise MapError(f"grid of {width}x{height} cells is too large (more than 1e8 cells)")
    data = np.full((height, width), UNKNOWN, dtype=np.int8)
    f = k_free - lo
    data[f[:, 1], f[:, 0]] = FREE
    o = k_occ - lo
    data[o[:, 1], o[:, 0]] = OCCUPIED
    origin = (float(lo[0] * resolution_m), float(lo[1] * resolution_m))
    return OccupancyGrid2D(data=data, resolution_m=float(resolution_m), origin_xy=origin,
                           map_from_world=T.copy())


def project_octree(octree: VoxelCentres, **kwargs: Any) -> OccupancyGrid2D:
    """`project_grid` of an `OccupancyOctree`'s occupied and free voxel centres.

    `resolution_m` defaults to the octree's; other keyword arguments are those of `project_grid`.
    """
    kwargs.setdefault("resolution_m", octree.resolution)
    T = kwargs.get("map_from_world")
    if hasattr(octree, "band_centres") and T is not None and np.array_equal(T, np.eye(4)):
        # the octree is in the map frame already: only the band's voxels need their centres (a
        # tenth of the map), the same numbers project_grid computes for them
        occ, free = octree.band_centres(kwargs["z_min_m"], kwargs["z_max_m"])
        return project_grid(occ, free, **kwargs)
    return project_grid(octree.occupied_centres(), octree.free_centres(), **kwargs)


# ---- map_server files ---------------------------------------------------------------------------


def _check_grid(grid: OccupancyGrid2D) -> np.ndarray:
    data = np.asarray(grid.data)
    if data.ndim != 2 or data.shape[0] < 1 or data.shape[1] < 1:
        raise MapError(f"grid data must be a non-empty (H, W) array, got shape {data.shape}")
    if data.dtype.kind not in "iu" or data.min() < -1 or data.max() > 100:
        raise MapError("grid data must be integers in [-1, 100]")
    return data


def pgm_bytes(grid: OccupancyGrid2D) -> bytes:
    """The grid as a binary PGM (P5) in map_server's trinary colours, first row = highest y.

    Like nav2's map_saver in trinary mode: 0..19 (below free_thresh) free, 65..100 occupied, the
    rest (-1 and the values between) unknown; our own grids only hold -1, 0 and 100.
    """
    data = _check_grid(grid)
    img = np.full(data.shape, PGM_UNKNOWN, dtype=np.uint8)
    img[(data >= 0) & (data < FREE_THRESH * 100)] = PGM_FREE
    img[data >= OCCUPIED_THRESH * 100] = PGM_OCCUPIED
    h, w = data.shape
    header = f"P5\n# CREATOR: octolog {grid.resolution_m:.3f} m/pix\n{w} {h}\n255\n".encode("ascii")
    return header + np.ascontiguousarray(img[::-1]).tobytes()


def yaml_text(grid: OccupancyGrid2D, image: str) -> str:
    """map_server YAML for the grid; `image` is the PGM path relative to the YAML file."""
    if "\n" in image or not image:
        raise MapError(f"invalid image file name {image!r}")
    ox, oy = grid.origin_xy
    return (
        f"image: {image}\n"
        "mode: trinary\n"
        f"resolution: {float(grid.resolution_m)!r}\n"
        f"origin: [{float(ox)!r}, {float(oy)!r}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
    )


def write_map_server(grid: OccupancyGrid2D, stem_path: str | os.PathLike[str]) -> dict[str, str]:
    """Write `stem.pgm` and `stem.yaml` (atomically, PGM first); returns {"pgm": ..., "yaml": ...}."""
    stem = Path(stem_path)
    pgm = stem.with_name(stem.name + ".pgm")
    yml = stem.with_name(stem.name + ".yaml")
    write_bytes_atomic(pgm, pgm_bytes(grid))
    write_bytes_atomic(yml, yaml_text(grid, pgm.name).encode("utf-8"))
    return {"pgm": str(pgm), "yaml": str(yml)}


# ---- nav_msgs/OccupancyGrid ---------------------------------------------------------------------


def occupancy_grid_msg(grid: OccupancyGrid2D, stamp_ns: int, frame_id: str = "map") -> OccupancyGrid:
    """A nav_msgs/msg/OccupancyGrid of the grid (rosbags type store).

    `info.origin` is the pose of cell (0, 0)'s lower-left corner in the map frame `frame_id`:
    position (origin_x, origin_y, 0), identity orientation. The map frame's relation to the
    mapper's world frame (`grid.map_from_world`) is not in the message: it is a transform
    (map <- world) for TF. `data` is row-major from (0, 0), i.e. `grid.data.ravel()`.
    """
    data = _check_grid(grid)
    Time = codec.msgtype("builtin_interfaces/msg/Time")
    Point = codec.msgtype("geometry_msgs/msg/Point")
    Quaternion = codec.msgtype("geometry_msgs/msg/Quaternion")
    Pose = codec.msgtype("geometry_msgs/msg/Pose")
    ox, oy = grid.origin_xy
    info = codec.msgtype("nav_msgs/msg/MapMetaData")(
        map_load_time=Time(sec=int(stamp_ns) // 1_000_000_000, nanosec=int(stamp_ns) % 1_000_000_000),
        resolution=float(grid.resolution_m),
        width=int(data.shape[1]),
        height=int(data.shape[0]),
        origin=Pose(position=Point(x=float(ox), y=float(oy), z=0.0),
                    orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
    )
    return codec.msgtype("nav_msgs/msg/OccupancyGrid")(
        header=codec.header(int(stamp_ns), frame_id), info=info,
        data=np.ascontiguousarray(data, dtype=np.int8).reshape(-1).copy(),
    )


def grid_from_msg(msg: OccupancyGrid, map_from_world: np.ndarray | None = None) -> OccupancyGrid2D:
    """The grid in a nav_msgs/msg/OccupancyGrid (as `occupancy_grid_msg` writes them).

    The message's float32 resolution is read back as the shortest decimal that gives the same
    float32 (0.05, not 0.0500000007). `map_from_world` is not in the message: pass it, or get
    the identity. Values other than -1, 0 and 100 are kept (other producers use 1..99).
    Raises MapError for a rotated origin or a data length that does not match width x height.
    """
    info = msg.info
    w, h = int(info.width), int(info.height)
    data = np.asarray(msg.data, dtype=np.int8).reshape(-1)
    if data.shape[0] != w * h:
        raise MapError(f"occupancy grid has {data.shape[0]} cells, expected {w}x{h}")
    o = info.origin.orientation
    if not np.allclose([o.x, o.y, o.z, abs(o.w)], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise MapError("occupancy grid origin is rotated; only axis-aligned grids are supported")
    res = float(str(np.float32(info.resolution)))
    if not (np.isfinite(res) and res > 0):
        raise MapError(f"occupancy grid resolution must be positive, got {res}")
    T = np.eye(4) if map_from_world is None else _check_transform(map_from_world).copy()
    return OccupancyGrid2D(data=data.reshape(h, w).copy(), resolution_m=res,
                           origin_xy=(float(info.origin.position.x), float(info.origin.position.y)),
                           map_from_world=T)
