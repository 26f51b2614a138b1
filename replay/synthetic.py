"""A synthetic, textured indoor room rendered on the CPU, with a known camera trajectory.

Used by the built-in demo and by tests. The room (synthetic_room) is a closed box with a few
objects, each face textured (synthetic_textures); the camera loops around the pillar
(synthetic_trajectory). Depth comes from `open3d.t.geometry.RaycastingScene` (ray parameter = z
depth), colour from a trilinear atlas lookup at the hit point (`cv2.remap`).

Nothing heavy happens at import or construction time: open3d, the geometry, the textures
(~1-2 s, shared by scenes with the same seed) and the ray caster are built on first use.

A frame costs ~0.1 s of CPU to render at 640x480, as much as the tracker spends on it: `render`
keeps each frame in octolog's cache (octolog.kit.cache, `synthetic/frames-KEY/`, colour and depth
as they are: 1.5 MB a frame at 640x480), keyed by everything that decides its bytes (the scene's
parameters but its length, this package's renderer source, the rendering libraries' versions).
Frame i does not depend on the sequence's length, so a longer run renders only the frames a
shorter one did not; a replay of a rendered sequence reads one file a frame. A scene with a depth
sensor (`depth_noise`) also keeps each frame's exact view (`synthetic/views-KEY/`: colour and float
depth before the sensor model, the motion blur and the blank stretch), so scenes that differ only
in those render the room once and pay ~15 ms a frame for the sensor.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from octolog.kit import cache, imu, opencv
from octolog.kit.geometry import Intrinsics, RgbdFrame, matrix_to_pose
from octolog.kit.up_vector import WINDOW_S, up_from_samples
from octolog.kit.opencv import baseline_simd
from octolog.replay import (depth_noise, synthetic_imu, synthetic_people, synthetic_room, synthetic_textures,
                            synthetic_trajectory)
from octolog.replay.source_gravity import simulated_up
from octolog.replay.synthetic_room import OBJECTS, ROOM, scene_faces, scene_triangles
from octolog.replay.synthetic_textures import Textures, scene_textures
from octolog.replay.synthetic_imu import SimulatedImu
from octolog.replay.synthetic_trajectory import MOTIONS, camera_trajectory

EPOCH_NS = 1_700_000_000 * 1_000_000_000
FRAME_FORMAT = 1  # the frame cache's layout: bump it when it changes (a new key)
# what renders a frame: these modules' source and these libraries' versions key the frame cache
_RENDERER = (__file__, depth_noise.__file__, synthetic_room.__file__, synthetic_textures.__file__,
             synthetic_trajectory.__file__, synthetic_people.__file__, opencv.__file__)
_RENDER_LIBRARIES = ("numpy", "open3d", "opencv-python-headless")
BLANK_GREY = 128  # the colour of a textureless stretch (`blank_s`)


@dataclass(frozen=True)
class SyntheticConfig:
    """Parameters of a synthetic sequence (see `SyntheticScene`)."""

    n_frames: int = 150
    width: int = 640
    height: int = 480
    seed: int = 0
    fps: float = 30.0
    fx: float | None = None  # default 525 * width / 640 (same field of view at any size)
    fy: float | None = None  # default 525 * width / 640
    cx: float | None = None  # default (width - 1) / 2
    cy: float | None = None  # default (height - 1) / 2
    min_depth_m: float = 0.1  # nearer hits read 0
    max_depth_m: float = 8.0  # farther hits read 0 (colour is still rendered)
    texel_m: float = 0.005  # texture resolution (finest mip level)
    mip_levels: int = 4  # texture pyramid levels (1 = no mip-mapping)
    start_ns: int = EPOCH_NS  # stamp of frame 0
    nthreads: int = 0  # ray-casting threads, 0 = all
    depth_noise: str = "none"  # none (exact, mm steps), kinect or d455: replay.depth_noise's models
    start_tilt_deg: float = 0.0  # the camera starts looking down this much more, level again after 1 s
    motion: str = "loop"  # loop (a walk round the pillar) or turns (the walk with fast head turns)
    path_start_s: float = 0.0  # the walk starts this far along its path (s)
    reverse: bool = False  # the walk goes the other way round
    exposure_ms: float = 0.0  # colour exposure: > 0 blurs colour by the camera's rotation over it
    depth_bias_px: float = 0.0  # the depth sensor's systematic disparity offset (replay.depth_noise.apply)
    imu_hz: float = 0.0  # > 0: a simulated D455 IMU at this rate (replay.synthetic_imu)
    # An IMU nobody calibrated (the consumer is told the datasheet's noise, the camera's axes, its clock):
    imu_noise_scale: float = 1.0  # its white noise and bias random walk, times the D455 datasheet's
    imu_rotation_deg: float = 0.0  # its axes turned this far from the colour camera's (synthetic_imu.MISMATCH_AXIS)
    imu_late_ms: float = 0.0  # each sample measures the motion this long before its stamp
    blank_at_s: float = 0.0  # with blank_s > 0: from this time on the colour camera sees no texture
    blank_s: float = 0.0  # for this long (a blank wall, a covered lens; depth is unchanged)
    people: str = ""  # people walking through the room (synthetic_people.crowd: cross, stand, round, close, joined with +)

    def __post_init__(self) -> None:
        """Checked once, where the parameters are built."""
        if self.n_frames < 0 or self.width <= 0 or self.height <= 0 or self.fps <= 0:
            raise ValueError(f"invalid synthetic scene parameters: {self}")
        if self.texel_m <= 0 or self.mip_levels < 1:
            raise ValueError(f"invalid synthetic scene texture parameters: {self}")
        if self.motion not in MOTIONS:
            raise ValueError(f"motion {self.motion!r}: want one of {', '.join(MOTIONS)}")
        if not 0.0 <= self.exposure_ms <= 1000.0 / self.fps:
            raise ValueError(f"exposure_ms {self.exposure_ms}: want 0 (no blur) up to the frame period")
        if self.depth_noise not in depth_noise.names():
            raise ValueError(f"depth_noise {self.depth_noise!r}: want one of {', '.join(depth_noise.names())}")
        if self.depth_bias_px and self.depth_noise == "none":
            raise ValueError("depth_bias_px: a disparity offset needs a depth sensor (depth_noise kinect or d455)")
        if self.imu_hz < 0 or self.blank_s < 0 or self.blank_at_s < 0:
            raise ValueError(f"imu_hz, blank_at_s, blank_s: want >= 0 (got {self.imu_hz}, {self.blank_at_s}, "
                             f"{self.blank_s})")
        if not (0.0 < self.imu_noise_scale <= 100.0 and abs(self.imu_rotation_deg) <= 90.0
                and abs(self.imu_late_ms) <= 1000.0 / self.fps):
            raise ValueError(f"imu_noise_scale, imu_rotation_deg, imu_late_ms: want 0-100 times, at most 90 deg and "
                             f"a frame period (got {self.imu_noise_scale}, {self.imu_rotation_deg}, {self.imu_late_ms})")
        if self.people:
            synthetic_people.crowd(self.people)  # raises ValueError naming the crowds there are
        if not abs(self.depth_bias_px) <= 1.0:
            raise ValueError(f"depth_bias_px {self.depth_bias_px}: want -1 to 1 px")


class SyntheticScene:
    """A synthetic RGB-D sequence of a textured room with ground-truth poses.

    Keyword arguments are those of `SyntheticConfig`. Frame i is stamped
    `start_ns + round(i * 1e9 / fps)` and rendered at pose `pose(i)` (world_from_camera,
    optical convention). Depth is uint16 millimetres (0 = no reading), colour uint8 RGB.
    """

    def __init__(
        self,
        *,
        n_frames: int = 150,
        width: int = 640,
        height: int = 480,
        seed: int = 0,
        fps: float = 30.0,
        **kwargs: Any,
    ) -> None:
        self.config = SyntheticConfig(
            n_frames=n_frames, width=width, height=height, seed=seed, fps=fps, **kwargs
        )
        cfg = self.config
        f = 525.0 * cfg.width / 640.0
        self.intrinsics = Intrinsics(
            width=cfg.width,
            height=cfg.height,
            fx=float(cfg.fx if cfg.fx is not None else f),
            fy=float(cfg.fy if cfg.fy is not None else f),
            cx=float(cfg.cx if cfg.cx is not None else (cfg.width - 1) / 2.0),
            cy=float(cfg.cy if cfg.cy is not None else (cfg.height - 1) / 2.0),
        )
        self.depth_scale_m = 0.001
        self.room = ROOM
        self.objects = OBJECTS

    def __len__(self) -> int:
        return self.config.n_frames

    # ---------------------------------------------------------------- timing and poses

    def _check(self, i: int) -> int:
        if not 0 <= i < self.config.n_frames:
            raise IndexError(f"frame {i} out of range [0, {self.config.n_frames})")
        return int(i)

    def stamp_ns(self, i: int) -> int:
        """Integer nanosecond stamp of frame i (exact 1/fps spacing, rounded)."""
        i = self._check(i)
        return self.config.start_ns + round(Fraction(i * 1_000_000_000) / Fraction(self.config.fps))

    @cached_property
    def _poses(self) -> np.ndarray:
        pos, rot = self._trajectory(np.arange(self.config.n_frames, dtype=float) / self.config.fps)
        T = np.tile(np.eye(4), (len(pos), 1, 1))
        T[:, :3, :3] = rot
        T[:, :3, 3] = pos
        T.setflags(write=False)
        return T

    def _trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        return camera_trajectory(t, start_tilt_deg=cfg.start_tilt_deg, motion=cfg.motion,
                                 path_start_s=cfg.path_start_s, reverse=cfg.reverse)

    def gravity_up(self) -> np.ndarray:
        """Up in frame 0's optical frame, from a simulated accelerometer on the camera: the
        simulated IMU's (`imu_hz`) samples within WINDOW_S of frame 0 when there is one."""
        sim = self.simulated_imu
        if sim is not None:
            t = sim.samples.stamp_ns
            near = np.abs(t - self.stamp_ns(0)) <= int(WINDOW_S * 1e9)
            up = up_from_samples(sim.samples.accel[near], np.eye(3), "the synthetic IMU")
            if up is not None:
                return up

        def rotation_at(t: float) -> np.ndarray:
            return self._trajectory(np.array([t]))[1][0]
        return simulated_up(rotation_at, 0.0, self.config.seed)

    @cached_property
    def simulated_imu(self) -> SimulatedImu | None:
        """The camera's IMU over the sequence (D455 noise, or the mismatched IMU's), None unless `imu_hz` > 0."""
        cfg = self.config
        if cfg.imu_hz <= 0:
            return None
        d, k = imu.D455, cfg.imu_noise_scale
        noise = imu.ImuNoise(d.gyro_noise * k, d.accel_noise * k, d.gyro_walk * k, d.accel_walk * k)
        turned = synthetic_imu.mismatch_rotation(cfg.imu_rotation_deg) if cfg.imu_rotation_deg else None
        return synthetic_imu.simulate(self._trajectory, max(cfg.n_frames - 1, 0) / cfg.fps, cfg.imu_hz, noise,
                                      cfg.seed, cfg.start_ns, turned, cfg.imu_late_ms * 1e-3)

    def pose(self, i: int) -> np.ndarray:
        """Ground-truth world_from_camera 4x4 of frame i (optical camera convention)."""
        return self._poses[self._check(i)].copy()

    def poses(self) -> np.ndarray:
        """All ground-truth poses, (n_frames, 4, 4)."""
        return self._poses.copy()

    def groundtruth_tum(self) -> str:
        """TUM trajectory text: '# timestamp tx ty tz qx qy qz qw' then one line per frame."""
        lines = ["# timestamp tx ty tz qx qy qz qw"]
        for i in range(self.config.n_frames):
            ns = self.stamp_ns(i)
            t, q = matrix_to_pose(self._poses[i])
            vals = " ".join(f"{x:.9f}" for x in (*t, *q))
            lines.append(f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} {vals}")
        return "\n".join(lines) + "\n"

    # ---------------------------------------------------------------- geometry

    @cached_property
    def mesh(self) -> Any:
        """The scene as an `open3d.geometry.TriangleMesh` (legacy), normals towards free space."""
        import open3d as o3d  # lazy: ~1.4 s to import, only rendering and geometry need it

        verts, tris, _ = scene_triangles()
        m = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(verts.copy()), o3d.utility.Vector3iVector(tris.copy())
        )
        m.compute_triangle_normals()
        return m

    @cached_property
    def _raycaster(self) -> Any:  # open3d's RaycastingScene (Any: open3d is imported lazily)
        import open3d as o3d  # lazy: ~1.4 s to import, only rendering and geometry need it

        verts, tris, _ = scene_triangles()
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32))
        )
        return scene

    def distance_to_surface(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) from each point (N, 3) to the nearest scene surface."""
        import open3d as o3d  # lazy: ~1.4 s to import, only rendering and geometry need it

        q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3))
        return self._raycaster.compute_distance(q).numpy().astype(np.float64)

    def surface_samples(self, spacing_m: float = 0.01) -> np.ndarray:
        """Points (N, 3) on a regular grid of about `spacing_m` over every visible surface.

        Parts of faces covered by an object (floor under a box, wall behind the cabinet) are left out.
        """
        if spacing_m <= 0:
            raise ValueError("spacing_m must be positive")
        out = []
        for face in scene_faces():
            nu = max(1, int(math.ceil(np.linalg.norm(face.u) / spacing_m)))
            nv = max(1, int(math.ceil(np.linalg.norm(face.v) / spacing_m)))
            a = (np.arange(nu) + 0.5) / nu
            b = (np.arange(nv) + 0.5) / nv
            pts = face.origin + a[:, None, None] * face.u + b[None, :, None] * face.v
            pts = pts.reshape(-1, 3)
            keep = np.ones(len(pts), dtype=bool)
            for j, box in enumerate(OBJECTS):
                if j != face.solid:
                    keep &= ~box.contains(pts)
            out.append(pts[keep])
        return np.concatenate(out, axis=0)

    # ---------------------------------------------------------------- rendering

    @cached_property
    def _textures(self) -> Textures:
        cfg = self.config
        return scene_textures(cfg.seed, cfg.texel_m, cfg.mip_levels)

    @cached_property
    def _rays_camera(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel ray directions (H*W, 3) in the camera frame with unit z (so t = depth),
        and the reciprocal of their lengths."""
        K = self.intrinsics
        u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
        d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
        return d.astype(np.float32), (1.0 / np.linalg.norm(d, axis=1)).astype(np.float32)

    def prepare(self) -> None:
        """Build the textures and ray caster now rather than on the first render."""
        _ = self._raycaster, self._textures, self._rays_camera

    def _sample(self, level: np.ndarray | int, prim: np.ndarray, tu: np.ndarray, tv: np.ndarray) -> np.ndarray:
        """Bilinear texture samples (N, 3) uint8 at level-0 texel coords (tu, tv) on mip `level`."""
        tx = self._textures
        flat = prim + level * tx.origin.shape[1]
        org = tx.origin.reshape(-1, 2).take(flat, axis=0)
        lim = tx.limit.reshape(-1, 2).take(flat, axis=0)
        if np.ndim(level) or level:
            scale = (np.float32(0.5) ** np.arange(self.config.mip_levels, dtype=np.float32))[level]
            tu, tv = tu * scale, tv * scale
        # Texel coordinates are >= 0 up to rounding; clamp to the face's own texture.
        rows = org[:, 0] + np.minimum(np.maximum(tu, 0.0), lim[:, 0])
        cols = org[:, 1] + np.minimum(np.maximum(tv, 0.0), lim[:, 1])
        # cv2.remap wants maps under 32767 rows/columns: lay the samples out 1024 to a row.
        n = len(rows)
        pad = -n % 1024
        rows, cols = np.pad(rows, (0, pad)), np.pad(cols, (0, pad))
        with baseline_simd():  # bilinear remap differs in the last bits between SIMD levels
            out = cv2.remap(
                tx.atlas, cols.reshape(-1, 1024), rows.reshape(-1, 1024), cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        return out.reshape(-1, 3)[:n]

    @cached_property
    def people(self) -> tuple[synthetic_people.Walker, ...]:
        """The people walking through the room (none in a static scene)."""
        return synthetic_people.crowd(self.config.people) if self.config.people else ()

    def render_pose(self, world_from_camera: np.ndarray, noise: np.random.Generator | None = None,
                    t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) uint8 and depth (H, W) uint16 mm seen from an arbitrary pose; with a
        `noise` generator and a `depth_noise` sensor, the depth that sensor would read; with `t` (s),
        the people in the room at that time in front of it."""
        rgb, z = self.view(world_from_camera, t)
        return rgb, self._sensed(rgb, z, noise)

    def view(self, world_from_camera: np.ndarray, t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) uint8 and exact depth (H, W) float32 m (inf where a ray hits nothing)
        seen from an arbitrary pose, with the people in the room at time `t` (s) when given."""
        import open3d as o3d  # lazy: ~1.4 s to import, only rendering and geometry need it

        cfg, K = self.config, self.intrinsics
        T = np.asarray(world_from_camera, dtype=np.float64)
        dirs_cam, inv_len = self._rays_camera
        rays = np.empty((K.width * K.height, 6), dtype=np.float32)
        rays[:, :3] = T[:3, 3]
        # Rotate the rays without BLAS (its spinning threads slow the ray caster down).
        R = T[:3, :3].astype(np.float32)
        for k in range(3):
            rays[:, 3 + k] = dirs_cam[:, 0] * R[k, 0] + dirs_cam[:, 1] * R[k, 1] + R[k, 2]
        ans = self._raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=cfg.nthreads)
        z = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy()
        bary = ans["primitive_uvs"].numpy()
        person = None
        if t is not None and self.people:
            pt, prgb = synthetic_people.cast(self.people, t, T[:3, 3], rays[:, 3:])
            person = pt < z  # misses are inf
            z = np.where(person, pt, z)
        exact = z  # every pixel's depth (below, z keeps the hits only)

        hit = np.isfinite(z)
        all_hit = bool(hit.all())
        dirs = rays[:, 3:]
        if not all_hit:
            prim, bary, z, dirs, inv_len = prim[hit], bary[hit], z[hit], dirs[hit], inv_len[hit]
        prim = prim.astype(np.int64)
        tx = self._textures
        c = tx.coef.take(prim, axis=0)
        b1, b2 = bary[:, 0], bary[:, 1]
        tu = c[:, 0] + b1 * c[:, 2] + b2 * c[:, 4]
        tv = c[:, 1] + b1 * c[:, 3] + b2 * c[:, 5]

        col = self._texture_colour(prim, tu, tv, z, dirs, inv_len)
        if all_hit:
            rgb = col
        else:
            rgb = np.zeros((len(hit), 3), dtype=np.uint8)
            rgb[hit] = col
        if person is not None:
            rgb[person] = prgb[person]
        return rgb.reshape(K.height, K.width, 3), exact.reshape(K.height, K.width)

    def _sensed(self, rgb: np.ndarray, z: np.ndarray, noise: np.random.Generator | None) -> np.ndarray:
        """uint16 depth (H, W) of the exact view (`z`, float32 m, inf for a miss): what the scene's
        `depth_noise` sensor reads with `noise`, else the exact depth rounded to the depth unit."""
        if noise is not None and self.config.depth_noise != "none":
            sensor = depth_noise.SENSORS[self.config.depth_noise]
            z = depth_noise.apply(z, rgb, sensor, noise, self.config.depth_bias_px)
        return self._depth_mm(z.ravel()).reshape(z.shape)

    def _texture_colour(self, prim: np.ndarray, tu: np.ndarray, tv: np.ndarray, z: np.ndarray, dirs: np.ndarray,
                        inv_len: np.ndarray) -> np.ndarray:
        """The texture's colour at each hit (triangle `prim`, texture coordinates `tu`, `tv`), trilinear
        mip-mapped when the scene has mip levels."""
        cfg, K, tx = self.config, self.intrinsics, self._textures
        levels = cfg.mip_levels
        if levels == 1:
            return self._sample(0, prim, tu, tv)
        # Trilinear mip-mapping; the level follows the pixel's footprint on the surface
        # (geometric mean of its two axes, the longer one stretched by the incidence angle).
        cos = np.abs(np.einsum("ij,ij->i", tx.normal.take(prim, axis=0), dirs)) * inv_len
        foot = z * np.float32(1.0 / (K.fx * cfg.texel_m)) / np.sqrt(np.maximum(cos, np.float32(0.02)))
        lod = np.clip(np.log2(np.maximum(foot, np.float32(1.0))), 0.0, levels - 1.0)
        l0 = np.minimum(lod.astype(np.int64), levels - 2)
        w = (lod - l0.astype(np.float32))[:, None]
        lower = self._sample(l0, prim, tu, tv).astype(np.float32)
        upper = self._sample(l0 + 1, prim, tu, tv).astype(np.float32)
        lower += (upper - lower) * w
        lower += np.float32(0.5)
        return lower.astype(np.uint8)

    def _depth_mm(self, z: np.ndarray) -> np.ndarray:
        """uint16 depth in depth_scale_m units; 0 outside [min_depth_m, max_depth_m] and for misses."""
        cfg = self.config
        ok = (z >= cfg.min_depth_m) & (z <= cfg.max_depth_m)  # False for misses (inf) and zeros
        depth = np.zeros(len(z), dtype=np.uint16)
        depth[ok] = np.rint(z[ok] * np.float32(1.0 / self.depth_scale_m)).astype(np.uint16)
        return depth

    def _motion_blur(self, i: int, rgb: np.ndarray) -> np.ndarray:
        """Colour as a camera exposing for `exposure_ms` around frame i's time sees it: the mean of
        the image turned by the camera's rotation at instants across the exposure (the rotation's
        homography K R K^-1; at 150 deg/s and 8 ms that is a 10-pixel smear). Translation's share of
        the blur (parallax) is left out: at walking speed it is under a pixel."""
        cfg, K = self.config, self.intrinsics
        t = i / cfg.fps + np.linspace(-0.5, 0.5, 9) * cfg.exposure_ms * 1e-3
        _, rot = self._trajectory(t)
        Km = np.array([[K.fx, 0.0, K.cx], [0.0, K.fy, K.cy], [0.0, 0.0, 1.0]])
        Ki = np.linalg.inv(Km)
        mid = self.pose(i)[:3, :3]
        acc = np.zeros(rgb.shape, np.float32)
        with baseline_simd():
            for r in rot:  # dst(p) = src(H p): the pixel p of the view at r, in the view at mid
                H = Km @ mid.T @ r @ Ki
                acc += cv2.warpPerspective(rgb, H, (K.width, K.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                           borderMode=cv2.BORDER_REPLICATE)
        return (acc * np.float32(1.0 / len(rot)) + np.float32(0.5)).astype(np.uint8)

    def _frame_config(self, **fixed: Any) -> SyntheticConfig:
        """The parameters that decide a frame's bytes (with `fixed` ones set): the sequence's length,
        the ray caster's thread count and the IMU do not."""
        return dataclasses.replace(self.config, n_frames=0, nthreads=0, imu_hz=0.0, imu_noise_scale=1.0,
                                   imu_rotation_deg=0.0, imu_late_ms=0.0, **fixed)

    @cached_property
    def _frame_folder(self) -> Path:
        """Where this scene's rendered frames are kept (see the module's docstring)."""
        key = cache.key_of((FRAME_FORMAT, self._frame_config()), [str(f) for f in _RENDERER], _RENDER_LIBRARIES)
        return cache.cache_root("synthetic") / f"frames-{key}"

    @cached_property
    def _view_folder(self) -> Path:
        """Where the exact views behind a depth sensor's frames are kept (`_exact_view`): scenes that
        differ only in the sensor model, the motion blur or the blank stretch share them."""
        cfg = self._frame_config(depth_noise="none", depth_bias_px=0.0, exposure_ms=0.0, blank_at_s=0.0, blank_s=0.0)
        key = cache.key_of((FRAME_FORMAT, "view", cfg), [str(f) for f in _RENDERER], _RENDER_LIBRARIES)
        return cache.cache_root("synthetic") / f"views-{key}"

    def _load(self, path: Path, depth_name: str, depth_dtype: type) -> tuple[np.ndarray, np.ndarray] | None:
        """Colour and depth kept at `path` (None when missing, unreadable or not this scene's shape)."""
        K = self.intrinsics
        kept = cache.load_arrays(path)
        if (kept is not None and set(kept) == {"rgb", depth_name} and kept["rgb"].shape == (K.height, K.width, 3)
                and kept["rgb"].dtype == np.uint8 and kept[depth_name].shape == (K.height, K.width)
                and kept[depth_name].dtype == depth_dtype):
            return kept["rgb"], kept[depth_name]
        return None

    def render(self, i: int) -> RgbdFrame:
        """The RGB-D frame i (seq = i) at its ground-truth pose (mid-exposure), from the frame cache
        when it is there (a missing or unreadable file is rendered again)."""
        i = self._check(i)
        path = self._frame_folder / f"{i:06d}.npz"
        kept = self._load(path, "depth", np.uint16)
        if kept is not None:
            rgb, depth = kept
        else:
            rgb, depth = self.render_frame(i)
            cache.store_arrays(path, {"rgb": rgb, "depth": depth})
        return RgbdFrame(
            seq=i,
            stamp_ns=self.stamp_ns(i),
            rgb=rgb,
            depth=depth,
            depth_scale_m=self.depth_scale_m,
            intrinsics=self.intrinsics,
        )

    def _exact_view(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """`view` of frame i (colour, exact depth), kept in the cache beside the frames: a depth
        sensor's frame is this view through the sensor model (~15 ms), where the view costs ~0.1 s."""
        path = self._view_folder / f"{i:06d}.npz"
        kept = self._load(path, "z", np.float32)
        if kept is not None:
            return kept
        rgb, z = self.view(self.pose(i), i / self.config.fps)
        cache.store_arrays(path, {"rgb": rgb, "z": z})
        return rgb, z

    def render_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Colour and depth of frame i, rendered (the frame cache's source): the view from its
        ground-truth pose, its sensor's depth noise, its motion blur, its blank stretch."""
        cfg = self.config
        if cfg.depth_noise != "none":
            rgb, z = self._exact_view(int(i))
            depth = self._sensed(rgb, z, np.random.default_rng([cfg.seed, int(i)]))
        else:
            rgb, depth = self.render_pose(self.pose(i), None, i / cfg.fps)
        if cfg.exposure_ms > 0:
            rgb = self._motion_blur(int(i), rgb)
        if cfg.blank_s > 0 and 0.0 <= i / cfg.fps - cfg.blank_at_s < cfg.blank_s:
            rgb = np.full_like(rgb, BLANK_GREY)
        return rgb, depth

    def frames(self) -> Iterator[RgbdFrame]:
        """All frames in order."""
        for i in range(self.config.n_frames):
            yield self.render(i)
