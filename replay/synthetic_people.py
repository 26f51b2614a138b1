"""People walking through the synthetic room: upright boxes of a person's size (0.28 m deep,
0.45 m across, 1.75 m tall) in textured clothes, moving along straight lines at walking speed, ray-cast analytically
on top of the static room (SyntheticScene.render_pose). The static room without them is the same
scene's twin: the same camera path, the same noise.

A crowd is named by the source option `people=NAME[+NAME...]`:
- `cross`: two people walk to and fro across the room, 1.1 and 1.25 m/s, away from the camera's
  path (a person passes 0.4-3 m in front of it);
- `stand`: one stands still for 5 s in view, then walks out of the room through a door in the
  +x wall (disappears there); the camera sees the spot again 10 s later;
- `round`: one walks round the room outside the camera's path, the same way round and faster (1.1
  m/s), overtaking it;
- `close`: one walks round the pillar inside the camera's path, the other way round: each time the
  two pass, the person fills most of the view (a stress case: 70 % of the view at the peak).

`Walker` is a piecewise-linear path of (time, x, y) knots, then gone; a path that repeats is
written out knot by knot. A function of time only, so frame i is the same whatever the sequence
length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

SIZE_M = (0.28, 0.45, 1.75)  # a person's box in their own axes: depth (the way they face), width, height
TEXEL_M = 0.02  # clothes' pattern cell
CROWDS = ("cross", "stand", "round", "close")


@dataclass(frozen=True)
class Walker:
    """A person: at knot times `t` (s, increasing) at floor positions `xy` (N, 2), moving linearly
    between knots, facing the way they go; absent before the first knot and after the last."""

    t: tuple[float, ...]
    xy: tuple[tuple[float, float], ...]
    seed: int

    def at(self, t: float) -> tuple[np.ndarray, float] | None:
        """Floor position (2,) and heading (rad) at time t, or None when absent."""
        ts = np.asarray(self.t)
        if not ts[0] <= t <= ts[-1]:
            return None
        xy = np.asarray(self.xy, dtype=float)
        k = int(min(np.searchsorted(ts, t, side="right") - 1, len(ts) - 2))
        a = (t - ts[k]) / max(ts[k + 1] - ts[k], 1e-9)
        pos = xy[k] + a * (xy[k + 1] - xy[k])
        step = xy[k + 1] - xy[k]
        j = k
        while not step.any() and j > 0:  # standing: face the way they came
            j -= 1
            step = xy[j + 1] - xy[j]
        j = k
        while not step.any() and j + 2 < len(xy):  # standing from the start: face the way they will go
            j += 1
            step = xy[j + 1] - xy[j]
        return pos, math.atan2(step[1], step[0])


def _to_and_fro(a: tuple[float, float], b: tuple[float, float], speed: float, start_s: float, until_s: float,
                seed: int) -> Walker:
    """Walking a <-> b at `speed` from `start_s` (at a) until `until_s`."""
    leg = math.dist(a, b) / speed
    n = int(math.ceil((until_s - start_s) / leg)) + 1
    return Walker(tuple(start_s + k * leg for k in range(n + 1)), tuple(a if k % 2 == 0 else b for k in range(n + 1)),
                  seed)


def _round_pillar(rx: float, ry: float, speed: float, until_s: float, seed: int, clockwise: bool) -> Walker:
    """Walking round an ellipse about the room's centre from angle 80 deg, clockwise seen from above
    (the camera goes anticlockwise) or not."""
    n = 48
    step = (1.0 if clockwise else -1.0) * 2.0 * math.pi / n
    arc = math.hypot(rx, ry) / math.sqrt(2.0) * abs(step)  # about the mean chord
    knots = int(math.ceil(until_s * speed / arc)) + 1
    th = math.radians(80.0) - step * np.arange(knots)
    return Walker(tuple(k * arc / speed for k in range(knots)),
                  tuple((rx * math.cos(v), ry * math.sin(v)) for v in th), seed)


@lru_cache(maxsize=None)
def crowd(name: str, until_s: float = 3600.0) -> tuple[Walker, ...]:
    """The walkers of `people=NAME[+NAME...]`."""
    out: list[Walker] = []
    for part in name.split("+"):
        if part == "cross":
            out += [_to_and_fro((-0.9, -1.45), (2.3, -1.45), 1.1, 0.0, until_s, 11),
                    _to_and_fro((-2.25, 0.9), (-2.25, -1.2), 1.25, 0.0, until_s, 12)]
        elif part == "stand":
            out.append(Walker((0.0, 5.0, 5.0 + 1.0 / 1.2), ((2.0, 0.5), (2.0, 0.5), (3.0, 0.5)), 13))
        elif part == "round":
            out.append(_round_pillar(2.0, 1.5, 1.1, until_s, 14, clockwise=False))
        elif part == "close":
            out.append(_round_pillar(0.7, 0.5, 1.1, until_s, 15, clockwise=True))
        else:
            raise ValueError(f"people {name!r}: want {'|'.join(CROWDS)}, joined with +")
    return tuple(out)


@lru_cache(maxsize=None)
def _clothes(seed: int) -> np.ndarray:
    """A person's clothes (rows: height from the floor, columns: round the body) as uint8 RGB, one
    texel per TEXEL_M: a shirt and trousers of random colours, blotched so that features catch."""
    rng = np.random.default_rng(seed)
    w, h = SIZE_M[0], SIZE_M[1]
    cols, rows = int(math.ceil(2 * (w + h) / TEXEL_M)), int(math.ceil(SIZE_M[2] / TEXEL_M))
    shirt, trousers, skin = rng.integers(40, 220, 3), rng.integers(20, 140, 3), np.array([205, 160, 130])
    base = np.empty((rows, cols, 3))
    z = (np.arange(rows) + 0.5) * TEXEL_M
    base[:] = np.where((z < 0.85)[:, None, None], trousers, np.where((z < 1.5)[:, None, None], shirt, skin))
    blotch = cv2.GaussianBlur(rng.normal(0.0, 1.0, (rows, cols)), (0, 0), 1.2)
    img = base * (1.0 + 0.45 * blotch / max(blotch.std(), 1e-9))[:, :, None]
    return np.clip(img, 0, 255).astype(np.uint8)


def cast(walkers: tuple[Walker, ...], t: float, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nearest person along each ray at time t: ray parameter (N,) float32 (inf: none), colour
    (N, 3) uint8. `origin` (3,) and `dirs` (N, 3) float32 in the world frame."""
    hit_t = np.full(len(dirs), np.inf, np.float32)
    rgb = np.zeros((len(dirs), 3), np.uint8)
    half = 0.5 * np.asarray(SIZE_M, np.float32)
    for walker in walkers:
        where = walker.at(t)
        if where is None:
            continue
        (x, y), yaw = where
        c, s = math.cos(yaw), math.sin(yaw)
        axes = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]], np.float32)  # rows: the body's axes
        o = axes @ (np.asarray(origin, np.float32) - np.array([x, y, half[2]], np.float32))
        if np.all(np.abs(o) <= half):
            continue  # the camera inside a person: not drawn
        d = dirs @ axes.T
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(1.0) / d
            t1, t2 = (-half - o) * inv, (half - o) * inv
        near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf).max(axis=1)
        far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf).min(axis=1)
        hit = (far >= near) & (near > 0) & (near < hit_t)
        if not hit.any():
            continue
        idx = np.flatnonzero(hit)
        tn = near[idx]
        p = o + tn[:, None] * d[idx]
        # round the body: front (+x), left (+y), back, right (top and bottom as the right), one strip of clothes
        u = np.select([p[:, 0] >= half[0] - 1e-4, p[:, 1] >= half[1] - 1e-4, p[:, 0] <= -half[0] + 1e-4],
                      [half[1] + p[:, 1], 2 * half[1] + half[0] - p[:, 0], 2 * half[1] + 2 * half[0] + half[1] - p[:, 1]],
                      4 * half[1] + 3 * half[0] + p[:, 0])
        tex = _clothes(walker.seed)
        col = np.clip((u / TEXEL_M).astype(np.int64), 0, tex.shape[1] - 1)
        row = np.clip(((p[:, 2] + half[2]) / TEXEL_M).astype(np.int64), 0, tex.shape[0] - 1)
        hit_t[idx] = tn
        rgb[idx] = tex[row, col]
    return hit_t, rgb


def boxes_at(walkers: tuple[Walker, ...], t: float) -> list[tuple[np.ndarray, float]]:
    """Where the people stand at time t: (floor position (2,), heading)."""
    return [w for walker in walkers if (w := walker.at(t)) is not None]


def inside(walkers: tuple[Walker, ...], t: float, points: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    """True for world points (N, 3) within a person's box (grown by `margin_m`) at time t."""
    pts = np.asarray(points, dtype=float)
    out = np.zeros(len(pts), bool)
    half = 0.5 * np.asarray(SIZE_M) + margin_m
    for (x, y), yaw in boxes_at(walkers, t):
        c, s = math.cos(yaw), math.sin(yaw)
        axes = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        local = (pts - np.array([x, y, 0.5 * SIZE_M[2]])) @ axes.T
        out |= np.all(np.abs(local) <= half, axis=1)
    return out
