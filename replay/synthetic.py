"""A synthetic, textured indoor room rendered on the CPU, with a known camera trajectory.

Used by the built-in demo and by tests. The room is a closed box (6 x 5 x 2.8 m, world frame z up,
floor at z = 0, walls at x = +-3 and y = +-2.5) holding a pillar, a table with a box on it, a
cabinet and two floor boxes. Every face carries its own procedural texture (value noise plus
several layers of randomly rotated coloured blocks and discs), baked once into a mip-mapped
texture atlas with view-independent shading, so a surface point always has the same colour (up to
mip-map filtering). Depth comes from `open3d.t.geometry.RaycastingScene` (ray parameter = z
depth), colour from a trilinear atlas lookup at the hit point (`cv2.remap`).

The camera (optical convention: x right, y down, z forward) loops on an ellipse around the
pillar (one loop in 18 s, 0.3-0.5 m/s, up to ~47 deg/s, 1.2-1.5 m high), looking roughly along its
path with a slow look-around; surfaces are 0.5-5 m away (median 2.4-3.6 m). The trajectory is a
function of time only, so frame i is the same whatever `n_frames` is.

Nothing heavy happens at import or construction time: open3d, the geometry, the textures
(~1-2 s, shared by scenes with the same seed) and the ray caster are built on first use.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from octolog.kit.geometry import Intrinsics, RgbdFrame, matrix_to_pose

ROOM_SIZE_M = (6.0, 5.0, 2.8)
EPOCH_NS = 1_700_000_000 * 1_000_000_000
_EPS = 1e-6


@dataclass(frozen=True)
class Box:
    """An upright box: footprint centre (x, y), bottom height z0, size (sx, sy, sz), yaw in rad."""

    x: float
    y: float
    z0: float
    sx: float
    sy: float
    sz: float
    yaw: float = 0.0

    def axes(self) -> np.ndarray:
        """Rows: the box's local x, y, z axes in world coordinates."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])

    def centre(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z0 + 0.5 * self.sz])

    def half(self) -> np.ndarray:
        return 0.5 * np.array([self.sx, self.sy, self.sz])

    def contains(self, p: np.ndarray, tol: float = _EPS) -> np.ndarray:
        """True for points (N, 3) inside or on the box (within tol)."""
        local = (np.asarray(p, dtype=float) - self.centre()) @ self.axes().T
        return np.all(np.abs(local) <= self.half() + tol, axis=1)

    def faces(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The six faces as (origin, U, V) rectangles with U horizontal where possible."""
        ax = self.axes()
        ex, ey, ez = ax[0] * self.sx, ax[1] * self.sy, ax[2] * self.sz
        c0 = self.centre() - 0.5 * (ex + ey + ez)
        return [
            (c0, ey, ez), (c0 + ex, ey, ez),  # -x, +x
            (c0, ex, ez), (c0 + ey, ex, ez),  # -y, +y
            (c0, ex, ey), (c0 + ez, ex, ey),  # bottom, top
        ]


ROOM = Box(0.0, 0.0, 0.0, *ROOM_SIZE_M)
OBJECTS: tuple[Box, ...] = (
    Box(0.0, 0.0, 0.0, 0.35, 0.35, ROOM_SIZE_M[2]),  # pillar, floor to ceiling
    Box(-1.9, 1.5, 0.0, 1.4, 0.8, 0.75, math.radians(10.0)),  # table-like block
    Box(-1.75, 1.45, 0.75, 0.32, 0.26, 0.3, math.radians(30.0)),  # box on the table
    Box(2.75, -0.8, 0.0, 0.5, 1.0, 1.9),  # cabinet flush against the +x wall
    Box(0.9, 1.95, 0.0, 0.6, 0.5, 0.45, math.radians(25.0)),  # low box
    Box(-1.5, -1.8, 0.0, 0.7, 0.6, 1.1, math.radians(-15.0)),  # tall box
)


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


@dataclass(frozen=True)
class _Face:
    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray  # unit, pointing into free space
    solid: int  # -1 for the room, else index into OBJECTS


# --------------------------------------------------------------------------- trajectory


def _trajectory(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (N, 3) and world_from_camera rotations (N, 3, 3) at times t (s)."""
    t = np.asarray(t, dtype=float)
    w = 2.0 * math.pi / 18.0  # one loop in 18 s
    th = w * t + math.radians(-100.0)
    ax, ay = 1.3, 0.9
    pos = np.stack(
        [ax * np.cos(th), ay * np.sin(th), 1.35 + 0.15 * np.sin(2.0 * math.pi * t / 7.0)], axis=1
    )
    heading = np.arctan2(ay * np.cos(th), -ax * np.sin(th))
    yaw = heading + math.radians(30.0) + math.radians(20.0) * np.sin(2.0 * math.pi * t / 7.3)
    pitch = math.radians(-8.0) + math.radians(7.0) * np.sin(2.0 * math.pi * t / 5.3 + 1.0)
    roll = math.radians(3.0) * np.sin(2.0 * math.pi * t / 4.1)
    # body frame: x forward, y left, z up; a positive pitch raises the view.
    body = Rotation.from_euler("ZYX", np.stack([yaw, -pitch, roll], axis=1)).as_matrix()
    optical_in_body = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return pos, body @ optical_in_body


# --------------------------------------------------------------------------- textures


def _hash01(ix: np.ndarray, iy: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic uniform [0, 1) value per integer cell (splitmix64 of the coordinates)."""
    x = (ix.astype(np.int64) + (1 << 30)).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    x ^= (iy.astype(np.int64) + (1 << 30)).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
    x ^= np.uint64(salt & 0xFFFFFFFFFFFFFFFF)
    x ^= x >> np.uint64(30)
    x *= np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(27)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def _cell_table(iu: np.ndarray, iv: np.ndarray, salt: int) -> np.ndarray:
    """`_hash01` of each integer cell (iu, iv), hashing each distinct cell of the range once."""
    u0, v0 = int(iu.min()), int(iv.min())
    gu = np.arange(u0, int(iu.max()) + 1, dtype=np.int64)[:, None]
    gv = np.arange(v0, int(iv.max()) + 1, dtype=np.int64)[None, :]
    table = _hash01(np.broadcast_to(gu, (gu.size, gv.size)), np.broadcast_to(gv, (gu.size, gv.size)), salt)
    return table.ravel().take((iu - u0) * gv.size + (iv - v0))


def _value_noise(u: np.ndarray, v: np.ndarray, cell: float, salt: int) -> np.ndarray:
    """Smooth value noise in [0, 1] on the separable grid u (nu, 1) x v (1, nv), feature size cell."""
    fu, fv = u / cell, v / cell
    iu, iv = np.floor(fu).astype(np.int64), np.floor(fv).astype(np.int64)
    a, b = fu - iu, fv - iv
    a, b = a * a * (3 - 2 * a), b * b * (3 - 2 * b)
    gu = np.arange(int(iu.min()), int(iu.max()) + 2, dtype=np.int64)[:, None]
    gv = np.arange(int(iv.min()), int(iv.max()) + 2, dtype=np.int64)[None, :]
    lat = _hash01(np.broadcast_to(gu, (gu.size, gv.size)), np.broadcast_to(gv, (gu.size, gv.size)), salt)
    # Interpolate along v on the lattice rows, then along u.
    jv = (iv - gv[0, 0]).ravel()
    rows = lat[:, jv] * (1 - b) + lat[:, jv + 1] * b  # (lattice u, nv)
    ju = (iu - gu[0, 0]).ravel()
    return (rows[ju] * (1 - a) + rows[ju + 1] * a).astype(np.float32)


def _face_texture(face: _Face, index: int, seed: int, texel: float) -> np.ndarray:
    """The baked (nu, nv, 3) float32 texture (0..255) of one face, texel (i, j) at (i, j) * texel."""
    rng = np.random.default_rng([seed, index, 0x5EED])
    salt = int(rng.integers(0, 2**62))
    lu, lv = float(np.linalg.norm(face.u)), float(np.linalg.norm(face.v))
    nu, nv = int(math.ceil(lu / texel)) + 1, int(math.ceil(lv / texel)) + 1
    uu = (np.arange(nu, dtype=np.float64) * texel)[:, None]
    vv = (np.arange(nv, dtype=np.float64) * texel)[None, :]

    palette = rng.uniform(0.05, 0.95, size=(6, 3)).astype(np.float32)
    n = _value_noise(uu, vv, rng.uniform(0.35, 0.7), salt + 1)[..., None]
    img = palette[0] * (1 - n) + palette[1] * n

    # Layers of randomly rotated coloured blocks, coarse to fine: corners at every scale.
    uu32, vv32 = uu.astype(np.float32), vv.astype(np.float32)
    scale = rng.uniform(0.8, 1.25)
    for k, (cell, p) in enumerate(((0.22, 0.45), (0.11, 0.4), (0.055, 0.3), (0.028, 0.22))):
        cell *= scale
        ang = rng.uniform(0.0, math.pi / 2)
        c, s = math.cos(ang) / cell, math.sin(ang) / cell
        ou, ov = rng.uniform(0.0, 1.0, size=2)
        iu = np.floor(np.float32(c) * uu32 + (np.float32(s) * vv32 + np.float32(ou))).astype(np.int32)
        iv = np.floor(np.float32(-s) * uu32 + (np.float32(c) * vv32 + np.float32(ov))).astype(np.int32)
        h = _cell_table(iu, iv, salt + 10 + k)
        on = h < p
        r = h[on] / p  # uniform [0, 1) again, given on
        pick = (r * len(palette)).astype(np.int64)
        bright = 0.3 + 0.75 * ((r * len(palette)) % 1.0)
        img[on] = np.clip(palette[pick] * bright[:, None].astype(np.float32), 0.0, 1.0)

    # Discs and rings of several sizes.
    n_discs = int(rng.poisson(6.0 * lu * lv)) + 2
    for _ in range(n_discs):
        r = math.exp(rng.uniform(math.log(0.025), math.log(0.15)))
        cu, cv = rng.uniform(0, lu), rng.uniform(0, lv)
        i0, i1 = max(0, int((cu - r) / texel)), min(nu, int((cu + r) / texel) + 2)
        j0, j1 = max(0, int((cv - r) / texel)), min(nv, int((cv + r) / texel) + 2)
        if i0 >= i1 or j0 >= j1:
            continue
        d2 = (uu[i0:i1] - cu) ** 2 + (vv[:, j0:j1] - cv) ** 2
        mask = d2 <= r * r
        if rng.random() < 0.35:
            mask &= d2 >= (0.55 * r) ** 2
        img[i0:i1, j0:j1][mask] = rng.uniform(0.05, 0.95, size=3)

    img += 0.06 * (_value_noise(uu, vv, 0.012, salt + 99)[..., None] - np.float32(0.5))

    img = _blur121(img)  # soften texel-sized steps

    # View-independent shading: ambient plus a fixed directional light.
    light = np.array([0.35, -0.25, -0.9])
    light /= np.linalg.norm(light)
    shade = 0.55 + 0.45 * abs(float(face.normal @ light))
    img *= np.float32(255.0 * shade)
    return np.clip(img, 0.0, 255.0)


def _blur121(img: np.ndarray) -> np.ndarray:
    """Separable [1 2 1] / 4 blur with edge replication."""
    p = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    p = 0.25 * p[:-2] + 0.5 * p[1:-1] + 0.25 * p[2:]
    return 0.25 * p[:, :-2] + 0.5 * p[:, 1:-1] + 0.25 * p[:, 2:]


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    """Mip levels: level l+1 texel i sits on level l texel 2i, [1 2 1]-filtered."""
    out = [img]
    for _ in range(levels - 1):
        prev = out[-1]
        nu, nv = (prev.shape[0] + 2) // 2, (prev.shape[1] + 2) // 2  # ceil((n-1)/2)+1
        p = np.pad(prev, ((0, 2 * nu - prev.shape[0]), (0, 2 * nv - prev.shape[1]), (0, 0)), mode="edge")
        out.append(_blur121(p)[: 2 * nu : 2, : 2 * nv : 2])
    return out


# --------------------------------------------------------------------------- the scene


@lru_cache(maxsize=1)
def _scene_faces() -> tuple[_Face, ...]:
    """Room faces (normals inward) then the visible faces of the objects (normals outward)."""
    faces: list[_Face] = []
    room_c = ROOM.centre()
    for o, u, v in ROOM.faces():
        n = np.cross(u, v)
        n /= np.linalg.norm(n)
        if n @ (room_c - (o + 0.5 * (u + v))) < 0:
            n = -n
        faces.append(_Face(o, u, v, n, -1))
    for k, box in enumerate(OBJECTS):
        bc = box.centre()
        for o, u, v in box.faces():
            fc = o + 0.5 * (u + v)
            # Faces lying on the room's shell or on another object can never be seen.
            on_shell = np.any(np.abs(np.abs(fc - room_c) - ROOM.half()) < _EPS)
            hidden = any(b.contains(fc[None])[0] for j, b in enumerate(OBJECTS) if j != k)
            if on_shell or hidden:
                continue
            n = np.cross(u, v)
            n /= np.linalg.norm(n)
            if n @ (fc - bc) < 0:
                n = -n
            faces.append(_Face(o, u, v, n, k))
    return tuple(faces)


@lru_cache(maxsize=1)
def _scene_triangles() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (4F, 3), triangles (2F, 3) wound towards free space, triangle -> face (2F,)."""
    verts, tris = [], []
    for f, face in enumerate(_scene_faces()):
        o, u, v = face.origin, face.u, face.v
        verts += [o, o + u, o + u + v, o + v]
        b = 4 * f
        if np.cross(u, v) @ face.normal > 0:
            tris += [[b, b + 1, b + 2], [b, b + 2, b + 3]]
        else:
            tris += [[b, b + 2, b + 1], [b, b + 3, b + 2]]
    out = (
        np.array(verts, dtype=np.float64),
        np.array(tris, dtype=np.int32),
        np.repeat(np.arange(len(verts) // 4), 2),
    )
    for a in out:
        a.setflags(write=False)
    return out


@dataclass(frozen=True)
class _Textures:
    atlas: np.ndarray  # (H, W, 3) uint8: every face's mip levels, packed on shelves
    origin: np.ndarray  # (levels, 2F, 2) float32: per level and triangle, atlas (row, col) of texel (0, 0)
    limit: np.ndarray  # (levels, 2F, 2) float32: (nu - 1, nv - 1) of that texture
    coef: np.ndarray  # (2F, 6) float32: level-0 texel coords of vertex 0 and of its two edges
    normal: np.ndarray  # (2F, 3) float32: triangle normals


def _pack_shelves(shapes: list[tuple[int, int]], width: int, gap: int = 2) -> tuple[list[tuple[int, int]], int]:
    """Top-left corners for rectangles (rows, cols) on shelves `width` wide; and the total height."""
    order = sorted(range(len(shapes)), key=lambda k: (-shapes[k][0], k))
    corners: list[tuple[int, int]] = [(0, 0)] * len(shapes)
    row = col = shelf = 0
    for k in order:
        h, w = shapes[k]
        if col + w > width:
            row, col, shelf = row + shelf + gap, 0, 0
        corners[k] = (row, col)
        col += w + gap
        shelf = max(shelf, h)
    return corners, row + shelf


@lru_cache(maxsize=2)
def _scene_textures(seed: int, texel: float, levels: int) -> _Textures:
    """Bake every face's texture pyramid into one atlas image (shared by scenes alike)."""
    faces = _scene_faces()
    verts, tris, tri_face = _scene_triangles()
    images = [_pyramid(_face_texture(face, f, seed, texel), levels) for f, face in enumerate(faces)]
    shapes = [img.shape[:2] for pyr in images for img in pyr]
    width = max(2048, max(w for _, w in shapes))
    corners, height = _pack_shelves(shapes, width)
    atlas = np.zeros((height, width, 3), dtype=np.uint8)
    origin = np.zeros((levels, len(faces), 2))
    limit = np.zeros((levels, len(faces), 2))
    k = 0
    for f, pyr in enumerate(images):
        for lv, img in enumerate(pyr):
            (r, c), (h, w) = corners[k], shapes[k]
            atlas[r : r + h, c : c + w] = np.rint(img)
            origin[lv, f], limit[lv, f] = (r, c), (h - 1, w - 1)
            k += 1
    coef = np.empty((len(tris), 6))
    for t, (tri, f) in enumerate(zip(tris, tri_face)):
        face = faces[f]
        uh = face.u / np.linalg.norm(face.u)
        vh = face.v / np.linalg.norm(face.v)
        rel = verts[tri] - face.origin
        uv = np.stack([rel @ uh, rel @ vh], axis=1) / texel
        coef[t] = [*uv[0], *(uv[1] - uv[0]), *(uv[2] - uv[0])]
    out = _Textures(
        atlas=atlas,
        origin=np.ascontiguousarray(origin[:, tri_face], dtype=np.float32),
        limit=np.ascontiguousarray(limit[:, tri_face], dtype=np.float32),
        coef=coef.astype(np.float32),
        normal=np.array([faces[f].normal for f in tri_face], dtype=np.float32),
    )
    for arr in (out.atlas, out.origin, out.limit, out.coef, out.normal):
        arr.setflags(write=False)
    return out


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
        if cfg.n_frames < 0 or cfg.width <= 0 or cfg.height <= 0 or cfg.fps <= 0:
            raise ValueError(f"invalid synthetic scene parameters: {cfg}")
        if cfg.texel_m <= 0 or cfg.mip_levels < 1:
            raise ValueError(f"invalid synthetic scene texture parameters: {cfg}")
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
        t = np.arange(self.config.n_frames, dtype=float) / self.config.fps
        pos, rot = _trajectory(t)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = rot
        T[:, :3, 3] = pos
        T.setflags(write=False)
        return T

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
        import open3d as o3d

        verts, tris, _ = _scene_triangles()
        m = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(verts.copy()), o3d.utility.Vector3iVector(tris.copy())
        )
        m.compute_triangle_normals()
        return m

    @cached_property
    def _raycaster(self) -> Any:
        import open3d as o3d

        verts, tris, _ = _scene_triangles()
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32))
        )
        return scene

    def distance_to_surface(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) from each point (N, 3) to the nearest scene surface."""
        import open3d as o3d

        q = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3))
        return self._raycaster.compute_distance(q).numpy().astype(np.float64)

    def surface_samples(self, spacing_m: float = 0.01) -> np.ndarray:
        """Points (N, 3) on a regular grid of about `spacing_m` over every visible surface.

        Parts of faces covered by an object (floor under a box, wall behind the cabinet) are left out.
        """
        if spacing_m <= 0:
            raise ValueError("spacing_m must be positive")
        out = []
        for face in _scene_faces():
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
    def _textures(self) -> _Textures:
        cfg = self.config
        return _scene_textures(cfg.seed, cfg.texel_m, cfg.mip_levels)

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
        import cv2

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
        out = cv2.remap(
            tx.atlas, cols.reshape(-1, 1024), rows.reshape(-1, 1024), cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        return out.reshape(-1, 3)[:n]

    def render_pose(self, world_from_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) uint8 and depth (H, W) uint16 mm seen from an arbitrary pose."""
        import open3d as o3d

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

        ok = (z >= cfg.min_depth_m) & (z <= cfg.max_depth_m)  # False for misses (inf)
        depth = np.zeros(len(z), dtype=np.uint16)
        depth[ok] = np.rint(z[ok] * np.float32(1.0 / self.depth_scale_m)).astype(np.uint16)

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

        levels = cfg.mip_levels
        if levels == 1:
            col = self._sample(0, prim, tu, tv)
        else:
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
            col = lower.astype(np.uint8)
        if all_hit:
            rgb = col
        else:
            rgb = np.zeros((len(hit), 3), dtype=np.uint8)
            rgb[hit] = col
        return rgb.reshape(K.height, K.width, 3), depth.reshape(K.height, K.width)

    def render(self, i: int) -> RgbdFrame:
        """The RGB-D frame i (seq = i) at its ground-truth pose."""
        rgb, depth = self.render_pose(self.pose(i))
        return RgbdFrame(
            seq=int(i),
            stamp_ns=self.stamp_ns(i),
            rgb=rgb,
            depth=depth,
            depth_scale_m=self.depth_scale_m,
            intrinsics=self.intrinsics,
        )

    def frames(self) -> Iterator[RgbdFrame]:
        """All frames in order."""
        for i in range(self.config.n_frames):
            yield self.render(i)
