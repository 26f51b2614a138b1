"""Map accuracy against ground-truth geometry (e.g. the synthetic scene).

Two measures:

- `cloud_to_surface`: distance from every point of a cloud to the true surface (mean, median,
  90th percentile, max), from an exact distance function or from dense surface samples.
- `voxel_accuracy`: how the occupancy map agrees with what the keyframes actually observed.
  `observed_voxels` derives that from ground-truth depth (the rendered depth at the true poses),
  not from the mapper, so it knows nothing of the mapper's filters:

  * observed surface point: a back-projected ground-truth depth pixel (depth > 0) whose Euclidean
    distance from its camera centre is at most `max_range_m` (OctoMap's range test). This is
    the keyframes' frusta, range and occlusion;
  * observed surface voxel: a voxel with an observed surface point within half a voxel of its
    centre (in its inscribed ball), i.e. one the surface passes through, not merely clips at a
    corner or edge. A voxel a surface only grazes holds a sliver of it: rays through the rest of
    it mark it free, so whether it ends up occupied is a matter of discretisation, not accuracy.
    Such voxels are in neither set (`core_radius` >= sqrt(3)/2 counts them as surface voxels);
  * observed free voxel: a voxel holding a point of an observed ray strictly between the camera
    centre and its surface point (rays of every `ray_stride`-th pixel, sampled every
    `step_fraction` voxel), and at least one voxel away from the surface: neither a ground-truth
    surface voxel (one holding a point of `surface_samples` or an observed surface point) nor
    26-adjacent to one.

  `voxel_accuracy` then reports the fraction of observed surface voxels the map has occupied
  (completeness; target >= 98 %) and the fraction of observed free voxels it has occupied (false
  occupancy; target <= 1 %).

Voxels are the octree's: index k holds [k * res, (k + 1) * res) on each axis of the world frame
the map is built in. A plane lying exactly on voxel faces (the synthetic room's walls, floor and
ceiling at 5 cm multiples in the scene frame) is degenerate: which of two voxels holds each of its
points is decided by 1 mm depth rounding, and every point is half a voxel from the centres, so the
core test drops most of them. Evaluate in a frame where that does not happen (e.g. the first
camera's frame, as the tracker's world is).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial import cKDTree

from octolog.kit.errors import MapError
from octolog.kit.geometry import RgbdFrame
from octolog.mapper.grid import VoxelCentres

__all__ = [
    "ObservedVoxels",
    "cloud_to_surface",
    "observed_from_scene",
    "observed_voxels",
    "voxel_accuracy",
    "voxel_keys",
]


class Scene(Protocol):
    """A scene with known geometry, as `observed_from_scene` reads it (replay's SyntheticScene)."""

    def pose(self, i: int) -> np.ndarray: ...

    def render(self, i: int) -> RgbdFrame: ...

    def surface_samples(self, spacing_m: float = 0.01) -> np.ndarray: ...


_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def _points(points: np.ndarray, name: str = "points") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MapError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise MapError(f"{name} contain NaN or infinite coordinates")
    return p


def _check_resolution(resolution_m: float) -> float:
    if not (np.isfinite(resolution_m) and resolution_m > 0):
        raise MapError(f"resolution must be a positive number, got {resolution_m}")
    return float(resolution_m)


# ---- cloud to surface ---------------------------------------------------------------------------


def cloud_to_surface(
    points: np.ndarray, surface: Callable[[np.ndarray], np.ndarray] | np.ndarray
) -> dict[str, float]:
    """Distances (m) from each point to the surface: {mean_m, median_m, p90_m, max_m, n_points}.

    `surface` is either a function giving the unsigned distance of each point (N, 3) -> (N,)
    (exact, e.g. `SyntheticScene.distance_to_surface`) or surface samples (M, 3), in which case the
    distance to the nearest sample is used (an over-estimate of up to half the sample spacing).
    """
    p = _points(points)
    if p.shape[0] == 0:
        raise MapError("cloud_to_surface needs at least one point")
    if callable(surface):
        d = np.asarray(surface(p), dtype=np.float64).reshape(-1)
        if d.shape[0] != p.shape[0] or not np.isfinite(d).all():
            raise MapError("surface distance function must return one finite distance per point")
    else:
        s = _points(surface, "surface samples")
        if s.shape[0] == 0:
            raise MapError("cloud_to_surface needs at least one surface sample")
        d, _ = cKDTree(s).query(p, k=1)
    return {
        "mean_m": float(np.mean(d)),
        "median_m": float(np.median(d)),
        "p90_m": float(np.percentile(d, 90)),
        "max_m": float(np.max(d)),
        "n_points": int(p.shape[0]),
    }


# ---- voxel bookkeeping --------------------------------------------------------------------------


def voxel_keys(points: np.ndarray, resolution_m: float) -> np.ndarray:
    """(N, 3) int64 voxel indices floor(p / resolution), OctoMap's voxel grid."""
    res = _check_resolution(resolution_m)
    return np.floor(_points(points) / res).astype(np.int64)


def _pack(keys: np.ndarray) -> np.ndarray:
    """One int64 per voxel index triple (each index within +-2^20)."""
    k = np.asarray(keys, dtype=np.int64).reshape(-1, 3) + _KEY_OFFSET
    if k.size and (k.min() < 0 or k.max() >= (1 << _KEY_BITS)):
        raise MapError("voxel indices out of range (more than 2^20 voxels from the origin)")
    return (k[:, 0] << (2 * _KEY_BITS)) | (k[:, 1] << _KEY_BITS) | k[:, 2]


def _unpack(packed: np.ndarray) -> np.ndarray:
    m = (1 << _KEY_BITS) - 1
    p = np.asarray(packed, dtype=np.int64)
    return np.stack([(p >> (2 * _KEY_BITS)) & m, (p >> _KEY_BITS) & m, p & m], axis=1) - _KEY_OFFSET


_NEIGHBOURS = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), axis=-1).reshape(-1, 3)


@dataclass(frozen=True, eq=False)
class ObservedVoxels:
    """Observed ground-truth voxels (sorted, unique (N, 3) int64 indices) at `resolution_m`."""

    resolution_m: float
    surface_keys: np.ndarray
    free_keys: np.ndarray

    def surface_centres(self) -> np.ndarray:
        return (self.surface_keys + 0.5) * self.resolution_m

    def free_centres(self) -> np.ndarray:
        return (self.free_keys + 0.5) * self.resolution_m


def observed_voxels(
    views: Iterable[tuple[np.ndarray, RgbdFrame]],
    *,
    resolution_m: float,
    max_range_m: float,
    surface_samples: np.ndarray,
    ray_stride: int = 8,
    step_fraction: float = 0.25,
    core_radius: float = 0.5,
) -> ObservedVoxels:
    """Observed surface and free voxels (see the module docstring) from ground-truth depth.

    `views` yields (world_from_camera 4x4, frame) with the frame's `depth` (integer units, 0 = no
    reading), `depth_scale_m` and pinhole `intrinsics` (distortion ignored, as the renderer has
    none). Every pixel within range is a surface point; a voxel is an observed surface voxel if one
    lies within `core_radius * resolution_m` of its centre (0.5: the inscribed ball; >= sqrt(3)/2
    counts every voxel a point falls in); every `ray_stride`-th pixel (rows and columns)
    casts a ray for free space, sampled every `step_fraction * resolution_m`. `surface_samples`
    (M, 3) are dense points on the whole true surface, in the same world frame, spaced well below
    the resolution (e.g. resolution / 4); they define the surface voxels free space keeps clear of.
    """
    res = _check_resolution(resolution_m)
    if not (np.isfinite(max_range_m) and max_range_m > 0):
        raise MapError(f"max_range_m must be positive, got {max_range_m}")
    if not isinstance(ray_stride, (int, np.integer)) or ray_stride < 1:
        raise MapError(f"ray_stride must be a positive integer, got {ray_stride!r}")
    if not (0 < core_radius):
        raise MapError(f"core_radius must be positive, got {core_radius}")
    if not (0 < step_fraction <= 1):
        raise MapError(f"step_fraction must be in (0, 1], got {step_fraction}")
    samples = _points(surface_samples, "surface samples")
    if samples.shape[0] == 0:
        raise MapError("observed_voxels needs ground-truth surface samples")
    step = step_fraction * res
    surf_parts: list[np.ndarray] = []
    touched_parts: list[np.ndarray] = []
    free_parts: list[np.ndarray] = []
    for T, frame in views:
        surf, touched, free = _view_voxels(T, frame, res, max_range_m, core_radius, ray_stride, step)
        surf_parts.append(surf)
        touched_parts.append(touched)
        free_parts.append(free)
    if not surf_parts:
        raise MapError("observed_voxels needs at least one view")
    surface = np.unique(np.concatenate(surf_parts))
    free = np.unique(np.concatenate(free_parts))
    # Keep free voxels at least one voxel away from the true surface (and the observed one).
    touched = np.unique(np.concatenate(touched_parts))
    near = np.concatenate([np.unique(_pack(np.floor(samples / res).astype(np.int64))), touched])
    near_keys = np.unique(near)
    dil = np.unique(_pack((_unpack(near_keys)[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 3)))
    free = free[~np.isin(free, dil, assume_unique=True)]
    return ObservedVoxels(resolution_m=res, surface_keys=_unpack(surface), free_keys=_unpack(free))


def _view_voxels(T: np.ndarray, frame: RgbdFrame, res: float, max_range_m: float, core_radius: float, ray_stride: int,
                 step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's packed keys: its surface-core voxels, every voxel a point falls in, the voxels its rays cross."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise MapError("view pose must be a finite 4x4 transform")
    K = frame.intrinsics
    depth = np.asarray(frame.depth)
    if depth.shape != (K.height, K.width):
        raise MapError(f"depth is {depth.shape[1]}x{depth.shape[0]}, intrinsics {K.width}x{K.height}")
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64) * float(frame.depth_scale_m)
    cam = np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=1)
    keep = np.linalg.norm(cam, axis=1) <= max_range_m
    cam, u, v = cam[keep], u[keep], v[keep]
    R, t = T[:3, :3], T[:3, 3]
    world = cam @ R.T + t
    keys = np.floor(world / res).astype(np.int64)
    core = np.linalg.norm(world - (keys + 0.5) * res, axis=1) <= core_radius * res
    ray = (u % ray_stride == 0) & (v % ray_stride == 0)
    return np.unique(_pack(keys[core])), np.unique(_pack(keys)), _ray_voxels(t, world[ray], res, step)


def _ray_voxels(origin: np.ndarray, ends: np.ndarray, res: float, step: float) -> np.ndarray:
    """Packed unique voxels of points o + s (e - o), s in [0, 1) sampled every `step` metres."""
    if ends.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    d = ends - origin
    length = np.linalg.norm(d, axis=1)
    n = np.ceil(length / step).astype(np.int64)  # samples s = j / n, j = 0 .. n-1
    out: list[np.ndarray] = []
    ends_at = np.cumsum(n)
    start = 0
    while start < len(n):  # chunks of about 2 million samples, at least one ray each
        base = int(ends_at[start - 1]) if start else 0
        stop = max(start + 1, int(np.searchsorted(ends_at, base + 2_000_000, side="right")))
        nn = n[start:stop]
        ray = np.repeat(np.arange(start, stop), nn)
        first = np.repeat(np.cumsum(nn) - nn, nn)
        s = (np.arange(int(nn.sum())) - first) / n[ray]
        pts = origin + s[:, None] * d[ray]
        out.append(np.unique(_pack(np.floor(pts / res).astype(np.int64))))
        start = stop
    return np.unique(np.concatenate(out))


def observed_from_scene(
    scene: Scene,
    frame_ids: Iterable[int],
    *,
    resolution_m: float,
    max_range_m: float,
    world_from_scene: np.ndarray | None = None,
    surface_spacing_m: float | None = None,
    ray_stride: int = 8,
    core_radius: float = 0.5,
) -> ObservedVoxels:
    """`observed_voxels` of a `SyntheticScene`'s frames, rendered at their ground-truth poses.

    The map's world frame is `world_from_scene` applied to the scene's (identity by default; the
    tracker's world is the first camera's frame: `inv(scene.pose(first))`). Surface samples are the
    scene's, `surface_spacing_m` apart (default resolution / 4).
    """
    W = np.eye(4) if world_from_scene is None else np.asarray(world_from_scene, dtype=np.float64)
    spacing = resolution_m / 4.0 if surface_spacing_m is None else surface_spacing_m
    samples = scene.surface_samples(spacing) @ W[:3, :3].T + W[:3, 3]

    def views():
        for i in frame_ids:
            yield W @ scene.pose(i), scene.render(i)

    return observed_voxels(views(), resolution_m=resolution_m, max_range_m=max_range_m,
                           surface_samples=samples, ray_stride=ray_stride, core_radius=core_radius)


# ---- voxel accuracy -----------------------------------------------------------------------------


def _occupied_packed(occupied: VoxelCentres | np.ndarray, res: float) -> np.ndarray:
    if hasattr(occupied, "occupied_centres"):
        map_res = float(getattr(occupied, "resolution", res))
        if not np.isclose(map_res, res, rtol=0, atol=1e-12):
            raise MapError(f"map resolution {map_res} differs from the observed voxels' {res}")
        centres = occupied.occupied_centres()
    else:
        centres = occupied
    c = _points(centres, "occupied centres")
    return np.unique(_pack(np.floor(c / res).astype(np.int64)))


def voxel_accuracy(occupied: VoxelCentres | np.ndarray, observed: ObservedVoxels) -> dict[str, float]:
    """Agreement of a map's occupied voxels with the observed ground truth.

    `occupied` is an `OccupancyOctree`-like object (`occupied_centres()`, `resolution`) or the
    occupied voxel centres (N, 3), on the same voxel grid as `observed`. Returns:

    - surface_voxels, surface_occupied, surface_occupied_fraction: observed surface voxels, and
      how many / which fraction of them the map has occupied (completeness);
    - free_voxels, free_occupied, free_occupied_fraction: observed free voxels, and how many /
      which fraction of them the map has occupied (false occupancy).
    - surface_free, surface_unknown (only for a map with `free_centres()`): the observed surface
      voxels the map has as free, and has never seen, for diagnosis.
    A fraction is NaN when its denominator is 0.
    """
    res = observed.resolution_m
    occ = _occupied_packed(occupied, res)
    surf = _pack(observed.surface_keys)
    free = _pack(observed.free_keys)
    s_occ = np.isin(surf, occ)
    s_hit = int(s_occ.sum())
    f_hit = int(np.isin(free, occ).sum())
    out: dict[str, float] = {
        "surface_voxels": int(surf.shape[0]),
        "surface_occupied": s_hit,
        "surface_occupied_fraction": s_hit / surf.shape[0] if surf.shape[0] else float("nan"),
        "free_voxels": int(free.shape[0]),
        "free_occupied": f_hit,
        "free_occupied_fraction": f_hit / free.shape[0] if free.shape[0] else float("nan"),
    }
    if hasattr(occupied, "free_centres"):
        map_free = np.unique(_pack(np.floor(_points(occupied.free_centres(), "free centres") / res).astype(np.int64)))
        s_free = int(np.isin(surf, map_free).sum())
        out["surface_free"] = s_free
        out["surface_unknown"] = int(surf.shape[0]) - s_hit - s_free
    return out
