"""ORB features for the RGB-D tracker: extraction spread over the image, depth lookup and matching.

Pure numpy/OpenCV, no state between frames: `RgbdSlam` (tracker/slam.py) and its parts own the map and call
these helpers.
Every step is deterministic (stable sorts with explicit tie-breaks, no hashing, no randomness).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from octolog.kit.errors import TrackingError
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.kit.opencv import baseline_simd

DESCRIPTOR_BYTES = 32


@dataclass(frozen=True)
class FrameFeatures:
    """Keypoints of one frame with descriptors, undistorted pixels and depth.

    `uv` are ideal (undistorted) pixel coordinates in the camera matrix of the intrinsics, so that
    every later step can use a plain pinhole projection. `z` is 0 where depth is missing or unsafe.
    """

    uv: np.ndarray  # (N, 2) float64 undistorted pixel coordinates
    octave: np.ndarray  # (N,) int32 pyramid level the keypoint was found on
    desc: np.ndarray  # (N, 32) uint8 ORB descriptors
    z: np.ndarray  # (N,) float64 depth in metres, 0 = invalid
    xyz: np.ndarray  # (N, 3) float64 point in the camera frame (zeros where z == 0)

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    @property
    def has_depth(self) -> np.ndarray:
        return self.z > 0.0


class OrbExtractor:
    """ORB keypoints bucketed on a grid so that texture-rich areas do not take the whole budget.

    Detects `oversample` times more corners than wanted, keeps the strongest few per grid cell
    (then the strongest leftovers up to `n_features`) and only then computes descriptors, which is
    cheaper than describing every candidate. As ORB-SLAM, FAST runs with a high threshold first
    (fewer, stronger corners, less work) and falls back to `min_fast_threshold` when that finds
    fewer than `n_features` corners (low texture, dark or blurred frames).
    """

    def __init__(
        self,
        *,
        n_features: int = 1000,
        grid_cols: int = 8,
        grid_rows: int = 6,
        oversample: float = 2.0,
        scale_factor: float = 1.2,
        n_levels: int = 8,
        fast_threshold: int = 20,
        min_fast_threshold: int = 7,
        edge_threshold: int = 19,
    ) -> None:
        self.n_features = n_features
        self.grid_cols = grid_cols
        self.grid_rows = grid_rows
        self.scale_factor = scale_factor
        self.n_levels = n_levels
        def orb(threshold: int) -> cv2.ORB:
            return cv2.ORB_create(
                nfeatures=max(n_features, int(round(n_features * oversample))),
                scaleFactor=scale_factor,
                nlevels=n_levels,
                edgeThreshold=edge_threshold,
                patchSize=31,
                fastThreshold=threshold,
            )

        self._orb = orb(fast_threshold)
        self._orb_low = orb(min_fast_threshold) if min_fast_threshold < fast_threshold else None

    def extract(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel positions (N, 2), octaves (N,) and descriptors (N, 32) of one grey image."""
        kps = self._orb.detect(gray, None)
        if len(kps) < self.n_features and self._orb_low is not None:
            kps = self._orb_low.detect(gray, None)
        if not kps:
            return _empty_extract()
        pts = cv2.KeyPoint_convert(kps).astype(np.float64)
        resp = np.array([k.response for k in kps], dtype=np.float64)
        keep = bucket_select(pts, resp, gray.shape[1], gray.shape[0], self.n_features, self.grid_cols, self.grid_rows)
        chosen = [kps[i] for i in keep]
        with baseline_simd():  # ORB's smoothing differs in the last bits between SIMD levels
            chosen, desc = self._orb.compute(gray, chosen)
        if desc is None or not chosen:
            return _empty_extract()
        pts = cv2.KeyPoint_convert(chosen).astype(np.float64).reshape(-1, 2)
        octave = np.array([k.octave for k in chosen], dtype=np.int32)
        # OpenCV's ORB reports a level-l keypoint at its level pixel times s = scale_factor^l; that
        # pixel's centre lies at (x + 0.5) s - 0.5 in the full image (the pyramid is a resize), so the
        # reported point sits 0.5 (s - 1) px up and left of the corner (1.3 px at level 7). Corrected:
        # on the synthetic room with exact truth the Sim(3) scale came 0.04-0.31 % short and ATE
        # 0.24-0.34 cm; corrected, within 0.12 % and 0.19-0.28 cm (docs/results.md, "Depth noise and scale")
        pts += 0.5 * (self.scale_factor ** octave - 1.0)[:, None]
        return pts, octave, np.ascontiguousarray(desc, dtype=np.uint8)


def _empty_extract() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros((0, DESCRIPTOR_BYTES), np.uint8)


def bucket_select(
    pts: np.ndarray, response: np.ndarray, width: int, height: int, n: int, cols: int, rows: int
) -> np.ndarray:
    """Indices of at most `n` points: the strongest per grid cell first, then the strongest rest.

    Ties in response are broken by the original index, so the choice is fully deterministic.
    """
    m = pts.shape[0]
    if m <= n:
        return np.arange(m)
    cx = np.clip((pts[:, 0] * cols / width).astype(np.int64), 0, cols - 1)
    cy = np.clip((pts[:, 1] * rows / height).astype(np.int64), 0, rows - 1)
    cell = cy * cols + cx
    idx = np.arange(m)
    # Order by cell, then by decreasing response, then by index (lexsort: last key is primary).
    order = np.lexsort((idx, -response, cell))
    cell_sorted = cell[order]
    first = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.arange(m) - first
    quota = -(-n // (cols * rows))
    in_quota = np.zeros(m, dtype=bool)
    in_quota[order] = rank < quota
    chosen = idx[in_quota]
    if chosen.size > n:
        # More cells than budget fits: keep the strongest of the per-cell picks.
        sub = np.lexsort((chosen, -response[chosen]))[:n]
        chosen = chosen[sub]
    elif chosen.size < n:
        rest = idx[~in_quota]
        sub = np.lexsort((rest, -response[rest]))[: n - chosen.size]
        chosen = np.concatenate([chosen, rest[sub]])
    return np.sort(chosen)


class Undistorter:
    """Maps raw pixel positions to ideal pinhole pixels of the same camera matrix (plumb-bob)."""

    def __init__(self, intrinsics: Intrinsics) -> None:
        self.K = intrinsics.matrix
        dist = np.asarray(intrinsics.distortion, dtype=np.float64)
        self.dist = dist if dist.size and np.any(dist != 0.0) else None

    def __call__(self, pts: np.ndarray) -> np.ndarray:
        if self.dist is None or pts.shape[0] == 0:
            return pts.astype(np.float64, copy=True)
        out = cv2.undistortPoints(
            pts.reshape(-1, 1, 2).astype(np.float64),
            self.K,
            self.dist,
            R=None,
            P=self.K,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-6),
        )
        return out.reshape(-1, 2).astype(np.float64)


def grey_image(frame: RgbdFrame) -> np.ndarray:
    """Grey image of a frame; TrackingError when its images do not match its intrinsics or each other."""
    intr = frame.intrinsics
    rgb, depth = frame.rgb, frame.depth
    if rgb.ndim not in (2, 3) or (rgb.ndim == 3 and rgb.shape[2] != 3) or rgb.dtype != np.uint8:
        raise TrackingError(f"frame {frame.seq}: colour must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if rgb.shape[:2] != (intr.height, intr.width):
        raise TrackingError(
            f"frame {frame.seq}: image is {rgb.shape[1]}x{rgb.shape[0]} but intrinsics say "
            f"{intr.width}x{intr.height}"
        )
    if depth.ndim != 2 or depth.shape != rgb.shape[:2]:
        raise TrackingError(f"frame {frame.seq}: depth {depth.shape} does not match colour {rgb.shape[:2]}")
    if not np.issubdtype(depth.dtype, np.integer):
        raise TrackingError(f"frame {frame.seq}: depth must be integer sensor units, got {depth.dtype}")
    if not (frame.depth_scale_m > 0.0 and math.isfinite(frame.depth_scale_m)):
        raise TrackingError(f"frame {frame.seq}: depth_scale_m={frame.depth_scale_m} must be positive")
    return rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def lookup_depth(
    depth: np.ndarray,
    depth_scale_m: float,
    pts: np.ndarray,
    *,
    min_depth_m: float,
    max_depth_m: float,
    max_spread: float,
) -> np.ndarray:
    """Metric depth at raw pixel positions, 0 where missing, out of range or on a depth edge.

    Corners often sit on object silhouettes where the depth pixel may belong to either surface;
    a 3x3 neighbourhood whose valid readings spread more than `max_spread` * depth is rejected
    because the point would be placed on the wrong surface.
    """
    n = pts.shape[0]
    if n == 0:
        return np.zeros(0)
    h, w = depth.shape
    u = np.clip(np.rint(pts[:, 0]).astype(np.int64), 1, w - 2)
    v = np.clip(np.rint(pts[:, 1]).astype(np.int64), 1, h - 2)
    offs = np.array([-1, 0, 1])
    patch = depth[(v[:, None] + offs)[:, :, None], (u[:, None] + offs)[:, None, :]].reshape(n, 9)
    patch = patch.astype(np.float64) * depth_scale_m
    z = patch[:, 4].copy()
    valid = patch > 0.0
    hi = np.where(valid, patch, -np.inf).max(axis=1)
    lo = np.where(valid, patch, np.inf).min(axis=1)
    ok = (z >= min_depth_m) & (z <= max_depth_m) & (valid.sum(axis=1) >= 6) & (hi - lo <= max_spread * z)
    return np.where(ok, z, 0.0)


def backproject(uv: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points of undistorted pixels at depth z (zeros where z == 0)."""
    xyz = np.zeros((uv.shape[0], 3))
    xyz[:, 0] = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    xyz[:, 1] = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    xyz[:, 2] = z
    return xyz


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance between two (K, 32) uint8 descriptor arrays."""
    return hamming64(as_words(a), as_words(b))


def as_words(desc: np.ndarray) -> np.ndarray:
    """(K, 32) uint8 descriptors viewed as (K, 4) uint64 words (no copy when contiguous)."""
    return np.ascontiguousarray(desc, dtype=np.uint8).view(np.uint64)


def hamming64(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance between two (K, 4) uint64 descriptor arrays."""
    c = np.bitwise_count(np.bitwise_xor(a, b))
    return c[:, 0].astype(np.int64) + c[:, 1] + c[:, 2] + c[:, 3]


def match_by_projection(
    proj_uv: np.ndarray,
    proj_desc: np.ndarray,
    kp_uv: np.ndarray,
    kp_desc: np.ndarray,
    *,
    radius: float | np.ndarray,
    max_distance: int,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one matches of projected map points to keypoints found within `radius` pixels.

    A grid of square cells of about half the max radius gives each projection the keypoints of the
    5 cell-row runs around it (each run is contiguous in cell order), so the cost grows with the
    candidates, not with (map points x keypoints). A match needs Hamming distance <= max_distance
    and best < ratio * second best among its candidates; a keypoint claimed by several map points
    goes to the closest descriptor.
    Returns (map index, keypoint index, Hamming distance), sorted by map index.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    m, n = proj_uv.shape[0], kp_uv.shape[0]
    if m == 0 or n == 0:
        return empty
    cand_map, cand_kp = _candidates_in_radius(proj_uv, kp_uv, radius)
    if cand_map.size == 0:
        return empty
    dist = _hamming_of_pairs(as_words(proj_desc), as_words(kp_desc), cand_map, cand_kp)

    # Best and second best per map point without sorting: candidates are grouped by map index
    # (each keypoint at most once per group), so a segmented minimum of (distance, keypoint index)
    # packed in one key finds the best (ties go to the lowest keypoint index); masking it out and
    # repeating gives the second.
    key = dist * n + cand_kp
    head = np.empty(cand_map.size, dtype=bool)
    head[0] = True
    np.not_equal(cand_map[1:], cand_map[:-1], out=head[1:])
    hi = np.flatnonzero(head)
    best = np.minimum.reduceat(key, hi)
    big = np.iinfo(key.dtype).max
    key[key == np.repeat(best, np.diff(hi, append=key.size))] = big
    second_key = np.minimum.reduceat(key, hi)
    bd = best // n
    good = (bd <= max_distance) & ((second_key == big) | (bd < ratio * (second_key // n)))
    bm, best, bd = cand_map[hi[good]], best[good], bd[good]
    if bm.size == 0:
        return empty
    bk = best - bd * n
    # One map point per keypoint: keep the smallest distance (ties: lowest map index). bm is
    # ascending and unique, so the winners stay sorted by map index.
    claim = bd * m + bm
    win = np.full(n, np.iinfo(claim.dtype).max)
    np.minimum.at(win, bk, claim)
    keep = win[bk] == claim
    return bm[keep].astype(np.int64), bk[keep].astype(np.int64), bd[keep].astype(np.int64)


def _candidates_in_radius(
    proj_uv: np.ndarray, kp_uv: np.ndarray, radius: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(map index, keypoint index) pairs within `radius` pixels, grouped by ascending map index."""
    m = proj_uv.shape[0]
    rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), (m,))
    # Cells of (max radius + 2 slack) / 2: the cell rows within radius + slack of a projection
    # are always 5. The slack (pixels) keeps the cell runs a superset under rounding; the exact
    # distance test follows.
    slack = 1e-3
    h = (max(float(rad.max()), 1.0) + 2.0 * slack) / 2.0
    kx = np.floor(kp_uv[:, 0] / h).astype(np.intp)
    ky = np.floor(kp_uv[:, 1] / h).astype(np.intp)
    x0, y0 = int(kx.min()), int(ky.min())
    ncols = int(kx.max()) - x0 + 1
    nrows = int(ky.max()) - y0 + 1
    kcell = (ky - y0) * ncols + (kx - x0)
    # The order within a cell does not matter: each map point's candidates are reduced with
    # unique keys.
    order = np.argsort(kcell)
    starts = np.zeros(nrows * ncols + 1, dtype=np.intp)
    np.cumsum(np.bincount(kcell, minlength=nrows * ncols), out=starts[1:])
    # Keypoints in cell order as u + iv: one gather and one subtraction give (du, dv).
    kz = np.empty(kp_uv.shape[0], dtype=np.complex128)
    kz.real, kz.imag = kp_uv[order, 0], kp_uv[order, 1]

    # Per projection and cell row: the run of cells [col_lo, col_hi) within radius + slack, which
    # is the run [lo, lo + count) of keypoints in cell order.
    pu, pv = proj_uv[:, 0], proj_uv[:, 1]
    r_s = rad + slack
    col_lo = np.clip(np.floor((pu - r_s) / h).astype(np.intp) - x0, 0, ncols)
    col_hi = np.clip(np.floor((pu + r_s) / h).astype(np.intp) - (x0 - 1), 0, ncols)
    row = (np.floor((pv - r_s) / h).astype(np.intp) - y0)[:, None] + np.arange(5)
    row_ok = (row >= 0) & (row < nrows)
    row_base = np.where(row_ok, row, 0) * ncols
    lo = starts[row_base + col_lo[:, None]]
    count = np.where(row_ok, starts[row_base + col_hi[:, None]] - lo, 0).ravel()
    end = np.cumsum(count)
    total = int(end[-1])
    if total == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    # Expand the runs: candidate j of run b is keypoint lo[b] + (j - first[b]) in cell order.
    pos = np.arange(total) + np.repeat(lo.ravel() - (end - count), count)
    per_map = np.diff(end[4::5], prepend=0)
    pz = np.empty(m, dtype=np.complex128)
    pz.real, pz.imag = pu, pv
    d = (kz[pos] - np.repeat(pz, per_map)).view(np.float64)
    d *= d
    cand_map = np.repeat(np.arange(m), per_map)
    r2 = float(rad[0]) * float(rad[0]) if np.ndim(radius) == 0 else (rad * rad)[cand_map]
    near = d[0::2] + d[1::2] <= r2
    return cand_map[near], order[pos[near]]


def _hamming_of_pairs(a: np.ndarray, b: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distances between rows a[ia] and b[ib] of (K, 4) uint64 words, as int64."""
    x = np.take(a, ia, axis=0)
    np.bitwise_xor(x, np.take(b, ib, axis=0), out=x)
    # The 4 per-word counts (<= 64 each) are the bytes of one uint32: add them pairwise.
    v = np.bitwise_count(x).view(np.uint32).ravel()
    v = (v & 0x00FF00FF) + ((v >> 8) & 0x00FF00FF)
    return ((v & 0xFFFF) + (v >> 16)).astype(np.int64)


def match_brute_force(
    query_desc: np.ndarray, train_desc: np.ndarray, *, max_distance: int, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one nearest-descriptor matches with a ratio test, for when no pose prior is usable.

    Returns (query index, train index, distance) sorted by query index.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    if query_desc.shape[0] == 0 or train_desc.shape[0] < 2:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    knn = matcher.knnMatch(query_desc, train_desc, k=2)
    rows = [
        (p[0].queryIdx, p[0].trainIdx, int(p[0].distance))
        for p in knn
        if len(p) == 2 and p[0].distance <= max_distance and p[0].distance < ratio * p[1].distance
    ]
    if not rows:
        return empty
    arr = np.array(rows, dtype=np.int64)
    q, t, dd = arr[:, 0], arr[:, 1], arr[:, 2]
    o = np.lexsort((q, dd, t))
    q, t, dd = q[o], t[o], dd[o]
    first = np.ones(t.size, dtype=bool)
    first[1:] = t[1:] != t[:-1]
    q, t, dd = q[first], t[first], dd[first]
    o = np.argsort(q, kind="stable")
    return q[o], t[o], dd[o]
