"""ORB features for the RGB-D tracker: extraction spread over the image, depth lookup and matching.

Pure numpy/OpenCV, no state between frames: `RgbdOdometry` owns the map and calls these helpers.
Every step is deterministic (stable sorts with explicit tie-breaks, no hashing, no randomness).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from octolog.geometry import Intrinsics

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
        chosen, desc = self._orb.compute(gray, chosen)
        if desc is None or not chosen:
            return _empty_extract()
        pts = cv2.KeyPoint_convert(chosen).astype(np.float64).reshape(-1, 2)
        octave = np.array([k.octave for k in chosen], dtype=np.int32)
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

    A coarse grid of cell size = max radius gives each projection the keypoints of its 3x3 cell
    block, so the cost grows with the candidates, not with (map points x keypoints). A match needs
    Hamming distance <= max_distance and best < ratio * second best among its candidates; a
    keypoint claimed by several map points goes to the closest descriptor.
    Returns (map index, keypoint index, Hamming distance), sorted by map index.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    m, n = proj_uv.shape[0], kp_uv.shape[0]
    if m == 0 or n == 0:
        return empty
    rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), (m,))
    cell = max(float(rad.max()), 1.0)
    kx = np.floor(kp_uv[:, 0] / cell).astype(np.int64)
    ky = np.floor(kp_uv[:, 1] / cell).astype(np.int64)
    x0, y0 = int(kx.min()) - 1, int(ky.min()) - 1
    ncols = int(kx.max()) - x0 + 2
    nrows = int(ky.max()) - y0 + 2
    kcell = (ky - y0) * ncols + (kx - x0)
    order = np.argsort(kcell, kind="stable")
    counts = np.bincount(kcell, minlength=ncols * nrows)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])

    px = np.floor(proj_uv[:, 0] / cell).astype(np.int64) - x0
    py = np.floor(proj_uv[:, 1] / cell).astype(np.int64) - y0
    d = np.array([-1, 0, 1])
    qx = np.repeat(px[:, None], 9, 1) + np.tile(d, 3)
    qy = np.repeat(py[:, None], 9, 1) + np.repeat(d, 3)
    inside = (qx >= 0) & (qx < ncols) & (qy >= 0) & (qy < nrows)
    qcell = np.where(inside, qy * ncols + qx, 0)
    qcount = np.where(inside, counts[qcell], 0).ravel()
    total = int(qcount.sum())
    if total == 0:
        return empty
    owner = np.repeat(np.arange(m * 9), qcount)
    block_first = np.cumsum(qcount) - qcount
    within = np.arange(total) - np.repeat(block_first, qcount)
    cand_kp = order[starts[qcell.ravel()][owner] + within]
    cand_map = owner // 9

    dx = kp_uv[:, 0][cand_kp] - proj_uv[:, 0][cand_map]
    dy = kp_uv[:, 1][cand_kp] - proj_uv[:, 1][cand_map]
    near = dx * dx + dy * dy <= (rad * rad)[cand_map]
    cand_map, cand_kp = cand_map[near], cand_kp[near]
    if cand_map.size == 0:
        return empty
    dist = hamming64(as_words(proj_desc)[cand_map], as_words(kp_desc)[cand_kp])

    # Best and second best per map point without sorting: candidates are already grouped by map
    # index, so a segmented minimum of (distance, keypoint index) packed in one key finds the best
    # (ties go to the lowest keypoint index); masking it out and repeating gives the second.
    key = dist * n + cand_kp
    head = np.ones(cand_map.size, dtype=bool)
    head[1:] = cand_map[1:] != cand_map[:-1]
    hi = np.flatnonzero(head)
    best = np.minimum.reduceat(key, hi)
    group = np.cumsum(head) - 1
    rest = np.where(key == best[group], np.iinfo(np.int64).max, key)
    second_key = np.minimum.reduceat(rest, hi)
    second = np.where(second_key == np.iinfo(np.int64).max, np.iinfo(np.int64).max, second_key // n)
    bm, bk, bd = cand_map[hi], best % n, best // n
    good = (bd <= max_distance) & (bd < ratio * second)
    bm, bk, bd = bm[good], bk[good], bd[good]
    if bm.size == 0:
        return empty
    # One map point per keypoint: keep the smallest distance (ties: lowest map index).
    o = np.lexsort((bm, bd, bk))
    bm, bk, bd = bm[o], bk[o], bd[o]
    first = np.ones(bk.size, dtype=bool)
    first[1:] = bk[1:] != bk[:-1]
    bm, bk, bd = bm[first], bk[first], bd[first]
    o = np.argsort(bm, kind="stable")
    return bm[o], bk[o], bd[o]


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
