"""The tracker's back end: local bundle adjustment, loop closing and the final global BA, as jobs.

`build_job` takes a self-contained snapshot of the map around the newest keyframe; `run_backend`
turns it into a `BackendResult` (moved keyframes and points, a closed loop) that the front end
(tracker/backend_handoff.py) applies at its next keyframe. A job touches nothing of the front end, so it runs
the same inline or in the worker process (tracker.worker), which is what keeps outputs byte-identical
with `background` on or off.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

from octolog.kit.geometry import invert
from octolog.tracker.bundle import BundleProblem, bundle_adjust
from octolog.tracker.config import OdometryParams
from octolog.tracker.features import FrameFeatures
from octolog.tracker.keyframe_map import METRES_PER_RADIAN, Keyframe, MapPoints
from octolog.kit.posegraph import optimize_pose_graph
from octolog.tracker.places import BowIndex, recognise
from octolog.tracker.pose import rotation_angle

# A keyframe sharing fewer map points than this with the new one is a loop candidate: the map lost
# track of that place and would only find it again by recognising it.
LOOP_MAX_SHARED_POINTS = 10


@dataclass
class BackendJob:
    kf_id: int
    poses_wc: np.ndarray  # (N, 4, 4) every keyframe
    ba: BundleProblem | None
    ba_kf: np.ndarray  # keyframe id of each BA pose
    ba_point_ids: np.ndarray  # map point id of each BA point
    iterations: int
    candidates: np.ndarray  # loop candidate keyframe ids
    new_feats: FrameFeatures
    cand_feats: list[FrameFeatures]
    covis: list[tuple[int, int]]  # pose-graph edges besides the consecutive ones
    loop_edges: list[tuple[int, int, np.ndarray]]
    xyz: np.ndarray | None  # all map points (only when loop closing may move them)
    ref_kf: np.ndarray | None  # the keyframe that created each of them
    min_votes: int
    min_inliers: int
    min_m: float
    min_rad: float
    max_m: float
    max_rad: float
    previous_candidate: np.ndarray | None
    consistency_m: float
    consistency_rad: float
    refine: tuple[np.ndarray, float, float]
    frozen_keyframes: int = 0  # the first this many (a saved map's) never move


@dataclass
class BackendResult:
    kf_id: int
    poses: dict[int, np.ndarray]  # moved keyframes
    point_ids: np.ndarray
    points: np.ndarray
    loop: tuple[int, int] | None = None
    loop_edge: tuple[int, int, np.ndarray] | None = None
    candidate: np.ndarray | None = None  # world correction asked by an unconfirmed loop


@dataclass(frozen=True)
class LoopState:
    """What the back end remembers between keyframes about loops (owned by the front end)."""

    edges: list[tuple[int, int, np.ndarray]]  # (old, new, old_from_new) of every closed loop
    last_loop_kf: int  # the newest keyframe of the last closed loop
    # the correction the previous keyframe's unconfirmed loop asked for, if it was the newest's predecessor
    previous_candidate: np.ndarray | None


def _ba_problem(mp: MapPoints, kfs: list[Keyframe], params: OdometryParams, K: np.ndarray, window_n: int,
                max_points: int | None, frozen: int = 0) -> tuple[BundleProblem | None, np.ndarray, np.ndarray]:
    """build_job's local BA: the problem over the newest `window_n` keyframes and their fixed
    neighbours, with the keyframes and point ids it covers (None and empty without local BA); the
    first `frozen` keyframes (a saved map's) are held wherever they fall."""
    ba_params = params.bundle_adjustment
    scale_factor = params.features.scale_factor
    n_kf = len(kfs)
    if not (params.local_ba and n_kf >= 2):
        return None, np.zeros(0, np.int64), np.zeros(0, np.int64)
    window = np.arange(max(0, n_kf - window_n), n_kf)
    pids = np.unique(np.concatenate([kfs[i].point_ids for i in window]))
    pids = pids[~mp.bad[pids]]
    if max_points is not None and pids.size > max_points:
        # the best-observed points carry the most information per factor: keep those
        n_obs = np.zeros(pids.size, np.int64)
        for i in window:
            n_obs += np.isin(pids, kfs[i].point_ids, assume_unique=True)
        pids = np.sort(pids[np.lexsort((pids, -n_obs))[:max_points]])
    # fixed neighbours: the earlier keyframes that created most of the window's points
    creators = mp.ref_kf[pids]
    counts = np.bincount(creators[creators < window[0]], minlength=n_kf)
    order = np.lexsort((np.arange(n_kf), -counts))
    n_fixed = ba_params.fixed_keyframes
    fixed = np.sort(order[:n_fixed][counts[order[:n_fixed]] > 0])
    ba_kf = np.concatenate([fixed, window])
    kf_idx, pt_idx, uv, zz, sig = [], [], [], [], []
    for li, i in enumerate(ba_kf):
        kf = kfs[i]
        pos = np.searchsorted(pids, kf.obs_pid)
        pos = np.minimum(pos, pids.size - 1)
        ok = pids[pos] == kf.obs_pid
        ok &= kf.feats.z[kf.obs_kp] > 0.0  # depth-less rays (near-parallel here) let points run off
        kp = kf.obs_kp[ok]
        kf_idx.append(np.full(kp.size, li))
        pt_idx.append(pos[ok])
        uv.append(kf.feats.uv[kp])
        zz.append(kf.feats.z[kp])
        sig.append(scale_factor ** kf.feats.octave[kp].astype(np.float64))
    ba = BundleProblem(
        poses_wc=np.stack([kfs[i].world_from_camera for i in ba_kf]),
        # as ORB-SLAM3 does: with fewer than two fixed neighbours (a new area) the oldest
        # window keyframe is held too, or the window would be free to drift as a whole
        fixed=np.array([i < window[0] or i == 0 or i < frozen or (fixed.size < 2 and i == window[0]) for i in ba_kf]),
        points=mp.xyz[pids].copy(),
        obs_kf=np.concatenate(kf_idx), obs_pt=np.concatenate(pt_idx), obs_uv=np.concatenate(uv),
        obs_z=np.concatenate(zz), obs_sigma=np.concatenate(sig),
        K=(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])),
        bf=1.0 / ba_params.inv_depth_sigma,
        **_gyro_factors(kfs, ba_kf),
    )
    return ba, ba_kf, pids


def _gyro_factors(kfs: list[Keyframe], ba_kf: np.ndarray) -> dict[str, np.ndarray]:
    """The gyro's rotations between the BA's keyframes (BundleProblem's rot_* fields)."""
    local = {int(k): li for li, k in enumerate(ba_kf)}
    rows = [(local[kfs[k].gyro[0]], li, kfs[k].gyro[1], kfs[k].gyro[2])  # type: ignore[index]
            for li, k in enumerate(ba_kf.tolist()) if kfs[k].gyro is not None and kfs[k].gyro[0] in local]
    if not rows:
        return {}
    return {"rot_pairs": np.array([(a, b) for a, b, _, _ in rows], np.int64),
            "rot_ab": np.stack([R for _, _, R, _ in rows]), "rot_sigma": np.array([s for _, _, _, s in rows])}


def _loop_candidates(mp: MapPoints, kfs: list[Keyframe], params: OdometryParams, bow: BowIndex | None,
                     loops: LoopState, loop_closing: bool) -> np.ndarray:
    """build_job's loop detection: the old keyframes the newest one may close a loop with."""
    lp = params.loops
    new = kfs[-1]
    n_kf = len(kfs)
    candidates = np.zeros(0, np.int64)
    if loop_closing and new.id - loops.last_loop_kf > lp.min_gap:
        # old keyframes that share (almost) no map points with the new one: a match with one
        # of them is a place seen again after the map lost track of it
        shared = np.bincount(mp.ref_kf[new.point_ids], minlength=n_kf)
        candidates = np.flatnonzero((np.arange(n_kf) <= new.id - lp.min_gap) & (shared < LOOP_MAX_SHARED_POINTS))
        if bow is not None and candidates.size:
            # ORB-SLAM's floor: a candidate must look at least as much like the new keyframe as the
            # least similar of the keyframes that share its points (else it is no better than any
            # view of this place; without covisible keyframes there is no floor)
            ids, scores = bow.query(keyframe=new.id, top=n_kf)  # every keyframe sharing a word, best first
            score = dict(zip(ids.tolist(), scores.tolist()))
            floor = min((score.get(j, 0.0) for j in new.covis), default=0.0)
            keep = np.isin(ids, candidates) & (scores >= floor)
            candidates = np.sort(ids[keep][: params.bow_candidates])
        elif candidates.size > params.bow_candidates:
            # without a vocabulary, the `bow_candidates` nearest by pose (position and viewing
            # direction, as the local map ranks keyframes): voting against every old keyframe cost
            # O(keyframes) per keyframe (synthetic turns: 80 % of the back end's time); drift of
            # a room-scale session still leaves the place seen again among the nearest
            pos = np.stack([kfs[i].world_from_camera[:3, 3] for i in candidates])
            axis = np.stack([kfs[i].world_from_camera[:3, 2] for i in candidates])
            T = new.world_from_camera
            score = np.linalg.norm(pos - T[:3, 3], axis=1) + \
                METRES_PER_RADIAN * np.arccos(np.clip(axis @ T[:3, 2], -1.0, 1.0))
            candidates = np.sort(candidates[np.lexsort((candidates, score))[: params.bow_candidates]])
    return candidates


def build_job(points: MapPoints, keyframes: list[Keyframe], params: OdometryParams, *, K: np.ndarray,
              bow: BowIndex | None, loops: LoopState, window_n: int, max_points: int | None, loop_closing: bool,
              iterations: int, frozen_keyframes: int = 0) -> BackendJob:
    """A self-contained snapshot for the back end of the newest keyframe: BA over the newest
    `window_n` keyframes with at most `max_points` points (None: all), `iterations` long, and loop
    detection if `loop_closing`; the first `frozen_keyframes` (a saved map's) never move."""
    mp, kfs = points, keyframes
    lp = params.loops
    scale_factor = params.features.scale_factor
    new = kfs[-1]
    n_kf = len(kfs)
    ba, ba_kf, ba_pids = _ba_problem(mp, kfs, params, K, window_n, max_points, frozen_keyframes)
    candidates = _loop_candidates(mp, kfs, params, bow, loops, loop_closing)
    return BackendJob(
        kf_id=new.id, poses_wc=np.stack([kf.world_from_camera for kf in kfs]), ba=ba, ba_kf=ba_kf,
        ba_point_ids=ba_pids, iterations=iterations, candidates=candidates,
        new_feats=new.feats, cand_feats=[kfs[i].feats for i in candidates],
        covis=[(i, j) for i in range(1, n_kf) for j in kfs[i].covis], loop_edges=list(loops.edges),
        # every map point and its creator: only a loop correction moves them all
        xyz=mp.xyz[: mp.size].copy() if candidates.size else None,
        ref_kf=mp.ref_kf[: mp.size].copy() if candidates.size else None,
        min_votes=lp.min_votes, min_inliers=lp.min_inliers, min_m=lp.min_correction_m,
        min_rad=math.radians(lp.min_correction_deg), max_m=lp.max_correction_m,
        max_rad=math.radians(lp.max_correction_deg),
        refine=(K, scale_factor, params.tracking.inv_depth_sigma),
        previous_candidate=loops.previous_candidate,
        consistency_m=lp.consistency_m, consistency_rad=math.radians(lp.consistency_deg),
        frozen_keyframes=frozen_keyframes,
    )


def apply_result(res: BackendResult, keyframes: list[Keyframe], points: MapPoints, kf_pos: np.ndarray,
                 kf_axis: np.ndarray, max_point_move_m: float,
                 frozen_points: int = 0) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Write a back-end result into the front end's map; returns how the job's newest keyframe moved
    (world_from_world) and every keyframe moved (id -> world_from_camera). The first
    `frozen_points` (a saved map's, seen from its fixed keyframes) keep their place.

    Keyframes inserted after the job was built (a live tracker that went on while the back end was
    busy) and the points they made move rigidly with the job's newest keyframe: they were placed
    relative to it, and a closed loop must carry them along."""
    if frozen_points and res.point_ids.size:
        mine = res.point_ids >= frozen_points
        res = dataclasses.replace(res, point_ids=res.point_ids[mine], points=res.points[mine])
    ref = keyframes[res.kf_id]
    old_ref = ref.world_from_camera.copy()
    moved = dict(res.poses)
    # how each keyframe the job moved moved (world_from_world), for the points it made that the job left out
    creator_delta = {i: T @ invert(keyframes[i].world_from_camera) for i, T in res.poses.items()}
    for i, T in res.poses.items():
        keyframes[i].world_from_camera = T
    delta = ref.world_from_camera @ invert(old_ref)
    for i in range(res.kf_id + 1, len(keyframes)):
        moved[i] = keyframes[i].world_from_camera = delta @ keyframes[i].world_from_camera
    for i, T in moved.items():
        kf_pos[i] = T[:3, 3]
        kf_axis[i] = T[:3, 2]
    if res.loop is None and res.point_ids.size:
        # a point that local BA moved far was badly observed: retire it rather than trust it
        moved_m = np.linalg.norm(res.points - points.xyz[res.point_ids], axis=1)
        jump = moved_m > max_point_move_m
        points.bad[res.point_ids[jump]] = True
        points.xyz[res.point_ids[~jump]] = res.points[~jump]
        _carry_left_out(points, res.point_ids, creator_delta)
    else:
        points.xyz[res.point_ids] = res.points
    if res.kf_id + 1 < len(keyframes):
        later = points.ref_kf[: points.size] > res.kf_id
        later[res.point_ids] = False
        ids = np.flatnonzero(later)
        points.xyz[ids] = points.xyz[ids] @ delta[:3, :3].T + delta[:3, 3]
    return delta, moved


def _carry_left_out(points: MapPoints, in_job: np.ndarray, creator_delta: dict[int, np.ndarray]) -> None:
    """Points local BA left out (beyond `max_points`) move rigidly with the keyframe that made them:
    left behind, a moved keyframe's own points no longer agreed with it (on a fast turn, reprojection
    errors of 10-20 px), and the next local BA pulled the keyframes apart to fit them."""
    if not creator_delta:
        return
    n = points.size
    left = np.isin(points.ref_kf[:n], np.array(sorted(creator_delta)))
    left[in_job] = False
    for i in sorted(creator_delta):
        ids = np.flatnonzero(left & (points.ref_kf[:n] == i))
        if ids.size:
            d = creator_delta[i]
            points.xyz[ids] = points.xyz[ids] @ d[:3, :3].T + d[:3, 3]


def run_backend(job: BackendJob) -> BackendResult:
    """Local BA around the newest keyframe, then loop detection and pose-graph correction.

    A step that fails numerically (gtsam's indeterminate system, degenerate geometry) is skipped:
    the back end improves the map when it can and never stops tracking. Failures depend only on
    the input, so skipping stays deterministic.
    """
    try:
        return _backend(job)
    except (RuntimeError, np.linalg.LinAlgError, cv2.error):
        if job.ba is None:
            return BackendResult(job.kf_id, {}, job.ba_point_ids, np.zeros((0, 3)))
        try:
            return _backend(dataclasses.replace(job, candidates=np.zeros(0, np.int64), cand_feats=[]))
        except (RuntimeError, np.linalg.LinAlgError, cv2.error):
            return BackendResult(job.kf_id, {}, np.zeros(0, np.int64), np.zeros((0, 3)))


def _backend(job: BackendJob) -> BackendResult:
    poses = job.poses_wc.copy()
    moved: dict[int, np.ndarray] = {}
    point_ids, points = job.ba_point_ids, np.zeros((0, 3))
    if job.ba is not None:
        res = bundle_adjust(job.ba, iterations=job.iterations)
        for li, i in enumerate(job.ba_kf):
            if not job.ba.fixed[li]:
                poses[i] = res.poses_wc[li]
                moved[int(i)] = res.poses_wc[li]
        points = res.points
    if job.candidates.size == 0:
        return BackendResult(job.kf_id, moved, point_ids, points)

    match = recognise(job.new_feats, job.candidates, job.cand_feats, min_votes=job.min_votes,
                      min_inliers=job.min_inliers, refine=job.refine)
    if match is None:
        return BackendResult(job.kf_id, moved, point_ids, points)
    old, new = match.keyframe, job.kf_id
    measured = match.T_kf_query  # old_from_new
    err = invert(invert(poses[old]) @ poses[new]) @ measured
    err_m, err_rad = float(np.linalg.norm(err[:3, 3])), rotation_angle(err[:3, :3])
    if err_m < job.min_m and err_rad < job.min_rad:
        return BackendResult(job.kf_id, moved, point_ids, points)  # the map already agrees
    if err_m > job.max_m or err_rad > job.max_rad:
        return BackendResult(job.kf_id, moved, point_ids, points)  # more than drift can explain
    # The correction this loop asks for, as a world-frame transform. A loop is closed only when
    # two consecutive keyframes ask for the same correction (as ORB-SLAM demands consistent
    # candidates): a single look-alike place cannot bend the map.
    C = poses[old] @ measured @ invert(poses[new])
    prev = job.previous_candidate
    if prev is None:
        return BackendResult(job.kf_id, moved, point_ids, points, candidate=C)
    here = poses[new][:3, 3]
    d = invert(prev) @ C
    if float(np.linalg.norm(C[:3, :3] @ here + C[:3, 3] - (prev[:3, :3] @ here + prev[:3, 3]))) > job.consistency_m \
            or rotation_angle(d[:3, :3]) > job.consistency_rad:
        return BackendResult(job.kf_id, moved, point_ids, points, candidate=C)
    rel = lambda i, j: invert(poses[i]) @ poses[j]  # noqa: E731
    edges = [(i - 1, i, rel(i - 1, i), 1.0) for i in range(1, len(poses))]
    edges += [(j, i, rel(j, i), 1.0) for i, j in job.covis]
    edges += [(i, j, T, 1.0) for i, j, T in job.loop_edges]
    edges.append((old, new, measured, 1.0))
    corrected = optimize_pose_graph(poses, edges, fixed=range(max(1, job.frozen_keyframes)))
    delta = corrected @ np.stack([invert(T) for T in poses])
    assert job.xyz is not None and job.ref_kf is not None
    xyz = job.xyz.copy()
    xyz[point_ids] = points
    d = delta[job.ref_kf]
    xyz = np.einsum("nij,nj->ni", d[:, :3, :3], xyz) + d[:, :3, 3]
    return BackendResult(job.kf_id, {i: corrected[i] for i in range(len(poses))}, np.arange(xyz.shape[0]), xyz,
                         (new, old), (old, new, measured))
