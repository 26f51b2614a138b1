"""Place recognition over keyframes: candidate search by descriptor voting, geometric verification.

Used for loop detection (a new keyframe against old ones it does not share map points with) and for
relocalisation (a frame against every keyframe after tracking was lost). A keyframe's place
signature is its ORB descriptor set; candidates are ranked by the number of one-to-one descriptor
matches that pass a ratio test, then verified in 3D: both sides carry depth, so a seeded RANSAC over
3-point rigid fits (Umeyama) finds the relative pose and its inliers. Everything is deterministic:
stable orderings, a fixed RNG seed, no dependence on timing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.metrics import umeyama_se3
from octolog.tracker.features import FrameFeatures, match_brute_force
from octolog.tracker.pose import optimize_pose
from octolog.tracker.vocab import Vocabulary

_SEED = 0x100C
# Descriptor matching between two views of a place: Hamming limit and best/second-best ratio, tighter
# than the tracker's projected matching (0.9) because nothing but the descriptor narrows the search.
PLACE_MAX_HAMMING = 64
PLACE_RATIO = 0.8
# Keypoints of the query that vote: enough to rank candidates, at a bounded cost per candidate.
VOTE_SUBSAMPLE = 400
# RANSAC over 3-point rigid fits: iterations, and the inlier distance at 1 m (grows with depth squared).
RIGID_RANSAC_ITERATIONS = 200
VERIFY_THRESHOLD_M = 0.03
# Repeated texture gives many matches of which a minority agree: a verified match needs a majority.
VERIFY_MIN_INLIER_RATIO = 0.5
# Loop and relocalisation verify at most this many best-voted candidates (verification is the costly step).
PLACES_VERIFIED = 3


@dataclass(frozen=True)
class PlaceMatch:
    """A verified match of a query view against a keyframe."""

    keyframe: int  # index of the keyframe in the list searched
    T_kf_query: np.ndarray  # (4, 4) pose of the query camera in the keyframe's camera frame
    query_idx: np.ndarray  # inlier keypoint indices in the query
    kf_idx: np.ndarray  # inlier keypoint indices in the keyframe
    n_matches: int
    n_inliers: int


def vote(query: FrameFeatures, candidates: list[FrameFeatures], *, max_distance: int = PLACE_MAX_HAMMING,
         ratio: float = PLACE_RATIO, subsample: int = VOTE_SUBSAMPLE) -> np.ndarray:
    """Number of ratio-test descriptor matches between the query and each candidate.

    Only the query's first `subsample` keypoints with depth vote (the extractor orders keypoints
    deterministically), which keeps the cost at O(candidates x subsample x features).
    """
    q = np.flatnonzero(query.has_depth)[:subsample]
    scores = np.zeros(len(candidates), np.int64)
    for c, feats in enumerate(candidates):
        qi, _, _ = match_brute_force(query.desc[q], feats.desc, max_distance=max_distance, ratio=ratio)
        scores[c] = qi.size
    return scores


def rigid_ransac(src: np.ndarray, dst: np.ndarray, *, threshold_m: float, iterations: int = RIGID_RANSAC_ITERATIONS,
                 seed: int = _SEED) -> tuple[np.ndarray, np.ndarray]:
    """T (4x4) with dst ~ T src from 3-point samples; returns (T, inlier mask). Deterministic.

    The threshold grows with depth (Kinect-type noise): `threshold_m * max(1, z_dst)**2`.
    """
    n = src.shape[0]
    best = np.zeros(n, dtype=bool)
    if n < 3:
        return np.eye(4), best
    rng = np.random.default_rng(seed)
    tol = threshold_m * np.maximum(1.0, dst[:, 2]) ** 2
    samples = np.stack([rng.choice(n, 3, replace=False) for _ in range(iterations)])
    # every hypothesis at once: Umeyama on each 3-point sample, then its inliers among all matches
    a, b = src[samples], dst[samples]  # (H, 3, 3)
    # a degenerate (near-collinear or repeated) sample, on either side, has no unique rotation
    area = np.minimum(np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1),
                      np.linalg.norm(np.cross(b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]), axis=1))
    ma, mb = a.mean(axis=1), b.mean(axis=1)
    cov = np.einsum("hki,hkj->hij", b - mb[:, None], a - ma[:, None]) / 3.0
    u, d, vt = np.linalg.svd(cov)
    valid = (area >= 1e-4) & (np.count_nonzero(d > np.finfo(d.dtype).eps, axis=1) >= 2)
    flip = np.linalg.det(u) * np.linalg.det(vt) < 0.0
    u[flip, :, 2] *= -1.0
    R = u @ vt
    t = mb - np.einsum("hij,hj->hi", R, ma)
    err = np.einsum("nj,hij->hni", src, R) + t[:, None, :] - dst[None]
    inl = np.einsum("hni,hni->hn", err, err) <= (tol * tol)[None]
    counts = np.where(valid, inl.sum(axis=1), 0)
    if counts.max() > 0:
        best = inl[int(np.argmax(counts))]  # the first of the best, as a sequential search keeps it
    T = np.eye(4)
    if best.sum() >= 3:
        for _ in range(2):  # refit on the inliers, then re-select them
            try:
                R, t = umeyama_se3(src[best], dst[best])
            except InputError:  # the inliers are collinear: no usable transform
                return np.eye(4), np.zeros(n, dtype=bool)
            inl = np.linalg.norm(src @ R.T + t - dst, axis=1) <= tol
            if inl.sum() < 3:
                break
            best = inl
        T[:3, :3], T[:3, 3] = R, t
    return T, best


def verify(query: FrameFeatures, kf: FrameFeatures, keyframe: int, *, min_inliers: int,
           threshold_m: float = VERIFY_THRESHOLD_M, min_inlier_ratio: float = VERIFY_MIN_INLIER_RATIO,
           refine: tuple[np.ndarray, float, float] | None = None) -> PlaceMatch | None:
    """Relative pose of the query in a keyframe's camera frame from 3D-3D matches, or None.

    With `refine` = (K, scale_factor, inv_depth_sigma) the RANSAC pose is refined on the inliers
    by the tracker's robust reprojection + inverse-depth optimisation, which is pixel-accurate
    where the 3D-3D fit is only as good as the depth noise.
    """
    qd, kd = np.flatnonzero(query.has_depth), np.flatnonzero(kf.has_depth)
    qi, ki, _ = match_brute_force(query.desc[qd], kf.desc[kd], max_distance=PLACE_MAX_HAMMING, ratio=PLACE_RATIO)
    if qi.size < min_inliers:
        return None
    qi, ki = qd[qi], kd[ki]
    n_matches = int(qi.size)
    T, inl = rigid_ransac(query.xyz[qi], kf.xyz[ki], threshold_m=threshold_m)
    n_inl = int(inl.sum())
    if n_inl < min_inliers or n_inl < min_inlier_ratio * qi.size:
        return None
    qi, ki = qi[inl], ki[inl]
    if refine is not None:
        K, scale, inv_depth_sigma = refine
        T_qk, ok = optimize_pose(np.linalg.inv(T), kf.xyz[ki], query.uv[qi],
                                 scale ** (-query.octave[qi].astype(np.float64)), query.z[qi], K,
                                 inv_depth_sigma=inv_depth_sigma)
        if int(ok.sum()) < min_inliers:
            return None
        T, qi, ki, n_inl = np.linalg.inv(T_qk), qi[ok], ki[ok], int(ok.sum())
    return PlaceMatch(keyframe, T, qi, ki, n_matches, n_inl)


def recognise(query: FrameFeatures, candidates: np.ndarray, cand_feats: list[FrameFeatures], *, min_votes: int,
              min_inliers: int, refine: tuple[np.ndarray, float, float] | None = None) -> PlaceMatch | None:
    """The first verified match among the best-voted `PLACES_VERIFIED` candidates (keyframe ids
    `candidates`, features `cand_feats`) with at least `min_votes` votes, or None. Ties by id."""
    scores = vote(query, cand_feats)
    order = np.lexsort((candidates, -scores))
    for o in order[:PLACES_VERIFIED]:
        if scores[o] < min_votes:
            break
        match = verify(query, cand_feats[o], int(candidates[o]), min_inliers=min_inliers, refine=refine)
        if match is not None:
            return match
    return None


def relocalisation_guess(feats: FrameFeatures, keyframes: Sequence[Any], bow: BowIndex | None, params: Any,
                         K: np.ndarray) -> np.ndarray | None:
    """world_from_camera of a lost frame from a place match against the keyframes (the vocabulary's
    `params.bow_candidates` best with one, else every keyframe), or None. `params`: OdometryParams."""
    t = params.tracking
    if int(feats.has_depth.sum()) < t.min_inliers or not keyframes:
        return None
    cands = np.arange(len(keyframes)) if bow is None else bow.query(feats.desc, top=params.bow_candidates)[0]
    match = recognise(feats, cands, [keyframes[c].feats for c in cands], min_votes=t.min_inliers,
                      min_inliers=t.min_inliers, refine=(K, params.features.scale_factor, t.inv_depth_sigma))
    return None if match is None else keyframes[match.keyframe].world_from_camera @ match.T_kf_query


class BowIndex:
    """A DBoW2-style keyframe database over a vocabulary tree (`tracker/vocab.py`).

    Each keyframe becomes an L1-normalised TF-IDF word vector; an inverted file maps words to the
    keyframes holding them, so a query touches only keyframes that share words with it, and scores
    them with DBoW2's L1 score (sum over shared words of min(a_w, b_w), 1 for identical vectors).
    With it, loop and relocalisation candidates are the best-scoring keyframes instead of all.
    """

    def __init__(self, vocabulary: Vocabulary) -> None:
        self._voc = vocabulary
        self._table = vocabulary.children_table()
        self._word_of_node = np.full(vocabulary.parents.shape[0], -1, dtype=np.int64)
        self._word_of_node[vocabulary.word_nodes] = np.arange(vocabulary.n_words)
        self._idf = vocabulary.weights[vocabulary.word_nodes]
        self._postings: dict[int, list[tuple[int, float]]] = {}
        self._vectors: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # each keyframe's, made once
        self.size = 0

    @property
    def vocabulary(self) -> Vocabulary:
        return self._voc

    def vector(self, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sorted word ids, L1-normalised TF-IDF weights) of a descriptor set."""
        if desc.shape[0] == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        words = self._word_of_node[self._voc.transform_nodes(desc, self._table)]
        w, counts = np.unique(words, return_counts=True)
        v = counts / counts.sum() * self._idf[w]
        total = v.sum()
        return w, (v / total if total > 0 else v)

    def add(self, keyframe: int, desc: np.ndarray) -> None:
        vec = self._vectors[keyframe] = self.vector(desc)
        for w, x in zip(*vec, strict=True):
            self._postings.setdefault(int(w), []).append((keyframe, float(x)))
        self.size += 1

    def query(self, desc: np.ndarray | None = None, *, top: int, allowed: np.ndarray | None = None,
              keyframe: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Best `top` keyframes (ids, scores), best first, ties by id; only `allowed` ids if given.
        The query is a descriptor set, or an added `keyframe` (its vector is not made again)."""
        scores: dict[int, float] = {}
        vec = self._vectors[keyframe] if keyframe is not None else self.vector(desc)
        for w, x in zip(*vec, strict=True):
            for kf, y in self._postings.get(int(w), ()):
                scores[kf] = scores.get(kf, 0.0) + min(x, y)
        ids = np.array(sorted(scores), dtype=np.int64)
        if allowed is not None:
            ids = ids[np.isin(ids, allowed)]
        sc = np.array([scores[int(i)] for i in ids])
        order = np.lexsort((ids, -sc))[:top]
        return ids[order], sc[order]
