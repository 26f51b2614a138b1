"""The synthetic room's geometry: a closed box (6 x 5 x 2.8 m, world frame z up, floor at z = 0,
walls at x = +-3 and y = +-2.5) holding a pillar, a table with a box on it, a cabinet and two floor
boxes, as the rectangles and triangles the renderer casts rays against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

ROOM_SIZE_M = (6.0, 5.0, 2.8)
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
class Face:
    """One rectangle of the scene: origin and edge vectors U, V (metres), its free-space normal."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray  # unit, pointing into free space
    solid: int  # -1 for the room, else index into OBJECTS


@lru_cache(maxsize=1)
def scene_faces() -> tuple[Face, ...]:
    """Room faces (normals inward) then the visible faces of the objects (normals outward)."""
    faces: list[Face] = []
    room_c = ROOM.centre()
    for o, u, v in ROOM.faces():
        n = np.cross(u, v)
        n /= np.linalg.norm(n)
        if n @ (room_c - (o + 0.5 * (u + v))) < 0:
            n = -n
        faces.append(Face(o, u, v, n, -1))
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
            faces.append(Face(o, u, v, n, k))
    return tuple(faces)


@lru_cache(maxsize=1)
def scene_triangles() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (4F, 3), triangles (2F, 3) wound towards free space, triangle -> face (2F,)."""
    verts, tris = [], []
    for f, face in enumerate(scene_faces()):
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
