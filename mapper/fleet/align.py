"""Where two robots' worlds lie relative to each other, from a place both have seen.

Each robot's tracker has its own world (its first camera frame). Without known start poses the
mapper relates them itself, as multi-session SLAM does (ORB-SLAM3's Atlas merging, RTAB-Map's
multi-session loop closures): a keyframe of a robot not yet placed is matched against the keyframes
already in the map. ORB features with a depth become 3D points in each camera; descriptor matches
(Lowe's ratio test, both ways) give 3D-3D pairs; a RANSAC over rigid transforms (Kabsch, a fixed
seed, so the same keyframes give the same answer) keeps the pairs that agree within a few
centimetres; the transform refitted to them is accepted only with many inliers that also cover the
image (a look-alike texture in one corner is not a place). The transform is then refined on the two
depth images (point-to-plane ICP, from 5 to 1.5 cm correspondences): ORB's 3D points sit on depth
edges and corners, where a Kinect-class depth is least sure; the surfaces pin the pose to millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from octolog.kit.geometry import RgbdFrame

N_FEATURES = 1000
RATIO = 0.8  # Lowe's ratio test
MIN_INLIERS = 60  # pairs that agree: a verified place, not a coincidence
MIN_INLIER_SHARE = 0.35  # of the mutual matches
MIN_SPREAD_PX = 30.0  # the inliers' spread in the image (std of x and y, each): a place, not a patch
INLIER_M = 0.03  # 3D distance for a pair to agree (Kinect-class depth noise at 1-2 m is ~1 cm)
ITERATIONS = 400
MIN_DEPTH_M, MAX_DEPTH_M = 0.2, 4.0


ICP_STRIDE = 4  # every 4th pixel of each depth image
ICP_DISTANCES_M = (0.05, 0.03, 0.015)
ICP_ITERATIONS = 8  # per distance


@dataclass(frozen=True)
class Features:
    """A keyframe's ORB descriptors with their 3D points in its camera frame and pixels, and its
    surface (points and normals from the depth image) for the refinement."""

    descriptors: np.ndarray  # (N, 32) uint8
    points: np.ndarray  # (N, 3) metres, camera frame
    pixels: np.ndarray  # (N, 2)
    surface: np.ndarray  # (M, 3)
    normals: np.ndarray  # (M, 3)


@dataclass(frozen=True)
class Alignment:
    a_from_b: np.ndarray  # 4x4: camera b's frame into camera a's
    inliers: int
    matches: int
    rmse_m: float


def features(frame: RgbdFrame, n: int = N_FEATURES) -> Features:
    gray = cv2.cvtColor(np.ascontiguousarray(frame.rgb), cv2.COLOR_RGB2GRAY)
    keypoints, desc = cv2.ORB_create(nfeatures=n).detectAndCompute(gray, None)
    surface, normals = _surface(frame)
    if desc is None or not keypoints:
        return Features(np.zeros((0, 32), np.uint8), np.zeros((0, 3)), np.zeros((0, 2)), surface, normals)
    px = np.array([k.pt for k in keypoints], dtype=np.float64)
    u, v = np.round(px[:, 0]).astype(int), np.round(px[:, 1]).astype(int)
    h, w = frame.depth.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = np.zeros(len(px))
    z[inside] = frame.depth[v[inside], u[inside]] * frame.depth_scale_m
    ok = (z > MIN_DEPTH_M) & (z < MAX_DEPTH_M)
    k = frame.intrinsics
    pts = np.stack([(px[ok, 0] - k.cx) * z[ok] / k.fx, (px[ok, 1] - k.cy) * z[ok] / k.fy, z[ok]], axis=1)
    return Features(desc[ok], pts, px[ok], surface, normals)


def _surface(frame: RgbdFrame) -> tuple[np.ndarray, np.ndarray]:
    """Points every ICP_STRIDE pixels and their normals from neighbouring pixels (the organised grid)."""
    s, k = ICP_STRIDE, frame.intrinsics
    z = frame.depth[::s, ::s].astype(np.float64) * frame.depth_scale_m
    h, w = z.shape
    u, v = np.meshgrid(np.arange(w) * s, np.arange(h) * s)
    P = np.stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z], axis=-1)
    du, dv = P[1:-1, 2:] - P[1:-1, :-2], P[2:, 1:-1] - P[:-2, 1:-1]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    zc = z[1:-1, 1:-1]
    ok = ((zc > MIN_DEPTH_M) & (zc < MAX_DEPTH_M) & (z[1:-1, 2:] > 0) & (z[1:-1, :-2] > 0) & (z[2:, 1:-1] > 0)
          & (z[:-2, 1:-1] > 0) & (norm[..., 0] > 1e-9))
    return P[1:-1, 1:-1][ok], (n / np.where(norm > 0, norm, 1.0))[ok]


def refine(a: Features, b: Features, a_from_b: np.ndarray) -> np.ndarray:
    """a_from_b refined by point-to-plane ICP of b's surface onto a's (Gauss-Newton, small angles)."""
    if len(a.surface) < 100 or len(b.surface) < 100:
        return a_from_b
    from scipy.spatial import cKDTree  # here: scipy.spatial costs 0.4 s of CPU to import, in every mapper

    tree = cKDTree(a.surface)
    T = a_from_b.copy()
    for dist in ICP_DISTANCES_M:
        for _ in range(ICP_ITERATIONS):
            Q = b.surface @ T[:3, :3].T + T[:3, 3]
            d, j = tree.query(Q, distance_upper_bound=dist)
            ok = np.isfinite(d)
            if ok.sum() < 100:
                return a_from_b
            q, p, n = Q[ok], a.surface[j[ok]], a.normals[j[ok]]
            A = np.hstack([np.cross(q, n), n])
            r = np.einsum("ij,ij->i", p - q, n)
            x = np.linalg.solve(A.T @ A + 1e-9 * np.eye(6), A.T @ r)
            step = np.eye(4)
            wx, wy, wz = x[:3]
            step[:3, :3] = cv2.Rodrigues(np.array([wx, wy, wz]))[0]
            step[:3, 3] = x[3:]
            T = step @ T
    return T


def _kabsch(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """4x4 T minimising |T(Q) - P| (rigid)."""
    cp, cq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((Q - cq).T @ (P - cp))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cp - R @ cq
    return T


def _mutual_matches(a: Features, b: Features) -> np.ndarray:
    """(K, 2) index pairs (a, b) that pass the ratio test both ways (none when fewer than
    MIN_INLIERS pass it one way: no place to verify)."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return np.zeros((0, 2), dtype=int)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)

    def one_way(x: np.ndarray, y: np.ndarray) -> dict[int, int]:
        out = {}
        for pair in bf.knnMatch(x, y, k=2):
            if len(pair) == 2 and pair[0].distance < RATIO * pair[1].distance:
                out[pair[0].queryIdx] = pair[0].trainIdx
        return out

    ab = one_way(a.descriptors, b.descriptors)
    if len(ab) < MIN_INLIERS:  # the mutual pairs are among these: too few for `align` either way
        return np.zeros((0, 2), dtype=int)
    ba = one_way(b.descriptors, a.descriptors)
    pairs = sorted((i, j) for i, j in ab.items() if ba.get(j) == i)
    return np.array(pairs, dtype=int).reshape(-1, 2)


def align(a: Features, b: Features, *, seed: int = 0) -> Alignment | None:
    """a_from_b if the two keyframes verifiably see the same place, refined on their surfaces, else None."""
    found = verify(a, b, seed=seed)
    return None if found is None else refined(a, b, found)


def refined(a: Features, b: Features, found: Alignment) -> Alignment:
    """`verify`'s alignment of a and b with its transform refined on their surfaces (`refine`)."""
    return replace(found, a_from_b=refine(a, b, found.a_from_b))


def verify(a: Features, b: Features, *, seed: int = 0) -> Alignment | None:
    """`align`'s answer before the refinement (its inliers and RMSE are the same): a caller choosing
    the best of several candidates refines only the one it keeps (`refined`), at ~0.3 s each."""
    pairs = _mutual_matches(a, b)
    if len(pairs) < MIN_INLIERS:
        return None
    P, Q = a.points[pairs[:, 0]], b.points[pairs[:, 1]]
    rng = np.random.default_rng(seed)
    best = np.zeros(len(pairs), dtype=bool)
    for _ in range(ITERATIONS):
        idx = rng.choice(len(pairs), 3, replace=False)
        T = _kabsch(P[idx], Q[idx])
        inl = np.linalg.norm(Q @ T[:3, :3].T + T[:3, 3] - P, axis=1) < INLIER_M
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < MIN_INLIERS:
        return None
    for _ in range(3):  # refit on the inliers, take them again
        T = _kabsch(P[best], Q[best])
        err = np.linalg.norm(Q @ T[:3, :3].T + T[:3, 3] - P, axis=1)
        best = err < INLIER_M
        if best.sum() < MIN_INLIERS:
            return None
    n = int(best.sum())
    spread = a.pixels[pairs[best, 0]].std(axis=0)
    if n < MIN_INLIER_SHARE * len(pairs) or spread.min() < MIN_SPREAD_PX:
        return None
    return Alignment(T, n, len(pairs), float(np.sqrt(np.mean(err[best] ** 2))))
