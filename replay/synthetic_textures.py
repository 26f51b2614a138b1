"""The synthetic room's textures: every face's own procedural texture (value noise plus several
layers of randomly rotated coloured blocks and discs), baked once into a mip-mapped atlas with
view-independent shading, so a surface point always has the same colour (up to mip-map filtering).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from octolog.kit import cache
from octolog.replay import synthetic_room
from octolog.replay.synthetic_room import Face, scene_faces, scene_triangles


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


def _face_texture(face: Face, index: int, seed: int, texel: float) -> np.ndarray:
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


@dataclass(frozen=True)
class Textures:
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


_FIELDS = ("atlas", "origin", "limit", "coef", "normal")


@lru_cache(maxsize=2)
def scene_textures(seed: int, texel: float, levels: int) -> Textures:
    """Every face's texture pyramid in one atlas (shared by scenes alike). Baking takes ~1.5 s, in
    every process that renders the room: the result is kept in octolog's cache (octolog.kit.cache),
    keyed by the arguments, this module's and the room's source and numpy's version."""
    key = cache.key_of((seed, texel, levels), (__file__, str(synthetic_room.__file__)), ("numpy",))
    path = cache.cache_root("synthetic") / f"textures-{key}.npz"
    kept = cache.load_arrays(path)
    if kept is not None and set(kept) == set(_FIELDS):
        out = Textures(**kept)
    else:
        out = _bake(seed, texel, levels)
        cache.store_arrays(path, {name: getattr(out, name) for name in _FIELDS})
    for name in _FIELDS:
        getattr(out, name).setflags(write=False)
    return out


def _bake(seed: int, texel: float, levels: int) -> Textures:
    """Bake every face's texture pyramid into one atlas image."""
    faces = scene_faces()
    verts, tris, tri_face = scene_triangles()
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
    return Textures(
        atlas=atlas,
        origin=np.ascontiguousarray(origin[:, tri_face], dtype=np.float32),
        limit=np.ascontiguousarray(limit[:, tri_face], dtype=np.float32),
        coef=coef.astype(np.float32),
        normal=np.array([faces[f].normal for f in tri_face], dtype=np.float32),
    )
