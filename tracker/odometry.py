"""RGB-D visual odometry: ORB features tracked against a small local map of keyframe points.

Per frame: extract ORB features spread over the image, read their depth, predict the pose with a
constant-velocity model, match projected local-map points around the prediction, estimate the
pose with `cv2.solvePnPRansac`, refine it with a robust (Huber) Gauss-Newton on reprojection and
inverse-depth residuals, then match the local map again with the refined pose and refine once
more. Keyframes add new map points and fuse repeated depth readings of existing ones, so drift is
only accumulated when the camera leaves the area the local map covers.

The core sees only `RgbdFrame`s and keyword tunables (no configuration trees, no I/O, no clock),
and is deterministic: the same frames give byte-identical poses in any process.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from octolog.kit.errors import TrackingError
from octolog.kit.geometry import Intrinsics, RgbdFrame, invert
from octolog.tracker.features import (
    DESCRIPTOR_BYTES,
    FrameFeatures,
    OrbExtractor,
    Undistorter,
    backproject,
    lookup_depth,
    match_brute_force,
    match_by_projection,
)
from octolog.tracker.optimize import BundleProblem, bundle_adjust, optimize_pose_graph
from octolog.tracker.worker import Worker

STATE_OK = "OK"
STATE_LOST = "LOST"
STATE_INIT = "INIT"
KP_UNMATCHED, KP_OUTLIER, KP_TRACKED, KP_NEW = 0, 1, 2, 3

# Chi-square 95% quantiles for 2 (pixel) and 3 (pixel + inverse depth) degrees of freedom.
_CHI2_2 = 5.991
_CHI2_3 = 7.815
_RANSAC_SEED = 0x0C70


@dataclass(frozen=True)
class TrackResult:
    """The tracker's answer for one frame."""

    seq: int
    stamp_ns: int
    world_from_camera: np.ndarray  # (4, 4) float64; world = first keyframe's camera frame
    state: str  # "OK" | "LOST" | "INIT"
    is_keyframe: bool
    keyframe_id: int  # -1 unless is_keyframe
    n_matches: int
    n_inliers: int
    # keyframes the back end moved (loop closure), id -> corrected world_from_camera; empty if none
    corrected: dict[int, np.ndarray] = field(default_factory=dict)
    # (new keyframe id, old keyframe id) of a loop closed at this frame
    loop: tuple[int, int] | None = None
    relocalised: bool = False
    # root mean square reprojection error of the inlier matches, in pixels of each keypoint's
    # pyramid level (a fit quality with no ground truth: ~1 for a model that explains the image)
    residual: float = float("nan")


# ----------------------------------------------------------------------------------------------
# Small SO(3) helpers (own Rodrigues so that nothing depends on library-internal branching).


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector."""
    theta = math.sqrt(float(w @ w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-10:
        return np.eye(3) + W
    a = math.sin(theta) / theta
    b = (1.0 - math.cos(theta)) / (theta * theta)
    return np.eye(3) + a * W + b * (W @ W)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (angles below pi)."""
    c = min(1.0, max(-1.0, (float(np.trace(R)) - 1.0) * 0.5))
    theta = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-10:
        return 0.5 * v
    return v * (theta / (2.0 * math.sin(theta)))


def rotation_angle(R: np.ndarray) -> float:
    """Angle in radians of a rotation matrix."""
    return math.acos(min(1.0, max(-1.0, (float(np.trace(R)) - 1.0) * 0.5)))


# ----------------------------------------------------------------------------------------------
# Robust pose refinement.


def optimize_pose(
    camera_from_world: np.ndarray,
    points_w: np.ndarray,
    uv: np.ndarray,
    inv_sigma_px: np.ndarray,
    z_meas: np.ndarray,
    K: np.ndarray,
    *,
    inv_depth_sigma: float,
    inliers: np.ndarray | None = None,
    rounds: int = 4,
    iterations: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine camera_from_world on 3D-2D matches; returns the pose and the final inlier mask.

    Residuals are the reprojection error in units of the keypoint's pyramid-level sigma and, where
    the keypoint has a depth reading, the inverse-depth error in units of `inv_depth_sigma`
    (1/m), which constrains translation along the optical axis that pixels alone see poorly.
    Gauss-Newton with Huber weights runs `rounds` times; between rounds observations are
    re-classified by a chi-square test so a wrong match cannot pull the pose (the scheme of
    ORB-SLAM's pose-only optimisation).
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R = camera_from_world[:3, :3].copy()
    t = camera_from_world[:3, 3].copy()
    n = points_w.shape[0]
    has_d = z_meas > 0.0
    inv_z_meas = np.where(has_d, 1.0 / np.where(has_d, z_meas, 1.0), 0.0)
    dsig = 1.0 / inv_depth_sigma
    thr = np.where(has_d, _CHI2_3, _CHI2_2)
    delta_h = np.sqrt(thr)
    active = np.ones(n, dtype=bool) if inliers is None else inliers.copy()
    # Per-observation constants gathered once per iteration: sigma scale, Huber delta and the
    # inverse-depth Jacobian factor (-dsig with depth, +0 without).
    per_obs = np.stack([inv_sigma_px, delta_h, np.where(has_d, -dsig, 0.0)]).T.copy()
    dsig_d = np.where(has_d, dsig, 0.0)

    def residuals(Rm: np.ndarray, tv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # r rows: u, v, inverse depth (3, n), so that the rows of the active points concatenate
        # to the Jacobian's row order with one gather.
        p = points_w @ Rm.T + tv
        z = p[:, 2]
        front = z > 1e-6
        iz = 1.0 / np.where(front, z, 1e-6)
        r = np.empty((3, n))
        np.multiply(fx * p[:, 0] * iz + cx - uv[:, 0], inv_sigma_px, out=r[0])
        np.multiply(fy * p[:, 1] * iz + cy - uv[:, 1], inv_sigma_px, out=r[1])
        np.multiply(iz - inv_z_meas, dsig_d, out=r[2])  # iz > 0: exactly +0 without depth
        sq = r * r
        chi2 = np.where(front, sq[0] + sq[1] + sq[2], np.inf)  # the order of a row sum
        return p, r, chi2

    res = None  # residuals at the current pose, when already computed
    for rnd in range(rounds):
        if int(active.sum()) < 6:
            break
        for _ in range(iterations):
            p, r, chi2 = residuals(R, t) if res is None else res
            res = None
            idx = np.flatnonzero(active & np.isfinite(chi2))
            m = idx.size
            if m < 6:
                break
            pa = np.take(p, idx, axis=0)
            x, y, z = pa[:, 0], pa[:, 1], pa[:, 2]
            obs = np.take(per_obs, idx, axis=0)
            s, dh, nd = obs[:, 0], obs[:, 1], obs[:, 2]
            iz = 1.0 / z
            xz, yz = x * iz, y * iz
            # Analytic Jacobians for the left perturbation p' = exp(phi) p + rho, columns
            # (rho, phi): rows u, v and inverse depth (zeroed where there is no depth). Entries
            # are written in place; the expressions keep the operand order of the formulas.
            J = np.zeros((3 * m, 6))
            Ju, Jv, Jd = J[:m], J[m : 2 * m], J[2 * m :]
            su, sv = s * fx, s * fy
            nsu, nsv = -su, -sv
            np.multiply(su, iz, out=Ju[:, 0])
            nsu_xz = nsu * xz
            np.multiply(nsu_xz, iz, out=Ju[:, 2])  # -su * xz * iz
            np.multiply(nsu_xz, yz, out=Ju[:, 3])  # -su * xz * yz
            np.multiply(su, 1.0 + xz * xz, out=Ju[:, 4])
            np.multiply(nsu, yz, out=Ju[:, 5])  # -su * yz
            np.multiply(sv, iz, out=Jv[:, 1])
            np.multiply(nsv * yz, iz, out=Jv[:, 2])  # -sv * yz * iz
            np.multiply(nsv, 1.0 + yz * yz, out=Jv[:, 3])  # -sv * (1 + yz^2)
            np.multiply(sv, xz, out=Jv[:, 5])
            np.multiply(Jv[:, 5], yz, out=Jv[:, 4])  # sv * xz * yz
            c2 = Jd[:, 2]
            np.multiply(iz * iz, nd, out=c2)  # -iz * iz * dsig with depth, +0 without
            np.multiply(y, c2, out=Jd[:, 3])
            np.multiply(x, -c2, out=Jd[:, 4])  # -x * c2 (same value, signed zeros included)
            rr = np.take(r, idx, axis=1).ravel()
            e = np.sqrt(np.take(chi2, idx))
            w = np.minimum(dh / np.maximum(e, 1e-12), 1.0)  # Huber: 1 where e <= dh
            Jw = (J.reshape(3, m, 6) * w[:, None]).reshape(3 * m, 6)
            H = Jw.T @ J
            g = Jw.T @ rr
            H.flat[::7] += 1e-9 + 1e-6 * H.diagonal()
            try:
                dx = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                break
            dR = so3_exp(dx[3:])
            R = dR @ R
            t = dR @ t + dx[:3]
            if float(dx @ dx) < 1e-10:  # below 10 micrometres / microradians
                break
        res = residuals(R, t)  # also the next round's first residuals
        new_active = res[2] <= thr
        if rnd > 0 and np.array_equal(new_active, active):
            break
        active = new_active
    # Re-orthonormalise: many small multiplicative updates accumulate rounding.
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    _, _, chi2 = residuals(R, t)
    return T, chi2 <= thr


def unroll_rolling_shutter(
    feats: FrameFeatures, rows: np.ndarray, height: int, K: np.ndarray, readout_s: float,
    step: tuple[np.ndarray, np.ndarray, int],
) -> FrameFeatures:
    """The keypoints as a global shutter at mid-readout would have seen them (rolling shutter).

    Image row r (`rows`: the keypoints' raw, distorted rows) is read `tau = (r / H - 1/2) * readout`
    after the middle row. With the camera's twist over `step` (rotation vector, translation in the
    camera frame, interval in ns), a point at camera position p at its row's time sits at
    p + tau (w x p + v) in the mid-readout camera frame (first order in tau). Keypoints with depth
    move in 3D; those without get the rotation's share only, which needs no range.
    """
    rotvec, trans, dt_ns = step
    if dt_ns <= 0 or readout_s == 0.0:
        return feats
    w = np.asarray(rotvec, np.float64) / (dt_ns * 1e-9)
    v = np.asarray(trans, np.float64) / (dt_ns * 1e-9)
    tau = (np.asarray(rows, np.float64) / height - 0.5) * readout_s
    has = feats.has_depth
    ray = np.column_stack([(feats.uv[:, 0] - K[0, 2]) / K[0, 0], (feats.uv[:, 1] - K[1, 2]) / K[1, 1],
                           np.ones(len(feats))])
    p = np.where(has[:, None], feats.xyz, ray)
    p0 = p + tau[:, None] * (np.cross(w, p) + np.where(has[:, None], v, 0.0))
    z0 = p0[:, 2]
    ok = z0 > 1e-6
    uv = feats.uv.copy()
    uv[ok, 0] = K[0, 0] * p0[ok, 0] / z0[ok] + K[0, 2]
    uv[ok, 1] = K[1, 1] * p0[ok, 1] / z0[ok] + K[1, 2]
    keep = has & ok
    return dataclasses.replace(feats, uv=uv, z=np.where(keep, z0, 0.0), xyz=np.where(keep[:, None], p0, 0.0))


# ----------------------------------------------------------------------------------------------
# Map storage.


class _MapPoints:
    """Growable column store of map points (world position, descriptor, bookkeeping)."""

    def __init__(self) -> None:
        self.size = 0
        cap = 4096
        self.xyz = np.zeros((cap, 3))
        self.desc = np.zeros((cap, DESCRIPTOR_BYTES), np.uint8)
        self.weight = np.zeros(cap)
        self.n_obs = np.zeros(cap, np.int32)
        self.n_visible = np.zeros(cap, np.int32)
        self.n_found = np.zeros(cap, np.int32)
        self.bad = np.zeros(cap, bool)
        self.ref_kf = np.zeros(cap, np.int64)  # keyframe that created the point

    def _grow(self, need: int) -> None:
        cap = self.xyz.shape[0]
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        for name in ("xyz", "desc", "weight", "n_obs", "n_visible", "n_found", "bad", "ref_kf"):
            old = getattr(self, name)
            arr = np.zeros((new_cap,) + old.shape[1:], old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def add(self, xyz: np.ndarray, desc: np.ndarray, weight: np.ndarray, ref_kf: int) -> np.ndarray:
        n = xyz.shape[0]
        self._grow(self.size + n)
        ids = np.arange(self.size, self.size + n)
        self.xyz[ids] = xyz
        self.desc[ids] = desc
        self.weight[ids] = weight
        self.n_obs[ids] = 1
        self.ref_kf[ids] = ref_kf
        self.size += n
        return ids


@dataclass
class _Keyframe:
    id: int
    seq: int
    world_from_camera: np.ndarray
    point_ids: np.ndarray  # sorted unique map point ids this keyframe observes
    feats: FrameFeatures  # all its keypoints (for bundle adjustment, loop detection, relocalisation)
    obs_kp: np.ndarray  # keypoint index of each observation
    obs_pid: np.ndarray  # map point id of each observation
    covis: list[int] = field(default_factory=list)  # earlier keyframes it shares many points with
    # Points of this keyframe matched in the first frame tracked after it: the overlap baseline
    # that later frames are compared with to decide when the view has changed enough.
    baseline_overlap: int = -1


@dataclass
class _Tracked:
    """Outcome of matching and pose estimation for one frame."""

    camera_from_world: np.ndarray
    kp_idx: np.ndarray  # keypoint indices of inlier matches
    map_idx: np.ndarray  # map point ids of inlier matches
    n_matches: int
    n_inliers: int
    feats: FrameFeatures  # the keypoints the pose was fitted to (moved to mid-readout: rolling shutter)
    residual: float = float("nan")  # RMS level-scaled reprojection error of the inliers


# ----------------------------------------------------------------------------------------------


class RgbdOdometry:
    """Frame-to-local-map RGB-D odometry. Call `track` once per frame, in time order.

    Tunables, by stage (defaults measured on TUM fr1/xyz at 640x480):
    features (`n_features`, grid, FAST threshold, pyramid), depth gating (range, edge spread),
    matching (`search_radius_px` around the motion prediction, `refine_radius_px` around the
    first pose, Hamming and ratio limits), pose (RANSAC threshold, `inv_depth_sigma` weighting
    depth against pixels, `min_inliers` below which a frame is LOST), keyframes (translation,
    rotation, overlap fraction) and the local map (keyframes near the pose plus the newest).
    `readout_s` is the colour camera's rolling-shutter readout time (0: global shutter): keypoints
    are moved to mid-readout with the camera's velocity, from the motion model for the first pose,
    then from the previous frame to that pose for the second matching pass and the final fit (see
    `unroll_rolling_shutter`). Invalid values raise TrackingError. One instance per camera
    stream; not thread-safe.
    """

    def __init__(
        self,
        *,
        n_features: int = 1000,
        grid_cols: int = 8,
        grid_rows: int = 6,
        fast_threshold: int = 20,
        min_fast_threshold: int = 7,
        n_levels: int = 8,
        scale_factor: float = 1.2,
        min_depth_m: float = 0.2,
        max_depth_m: float = 6.0,
        max_new_point_depth_m: float = 4.0,
        depth_edge_spread: float = 0.04,
        inv_depth_sigma: float = 0.03,
        search_radius_px: float = 15.0,
        refine_radius_px: float = 4.0,
        max_hamming: int = 80,
        match_ratio: float = 0.9,
        confident_ratio: float = 0.5,
        ransac_reproj_px: float = 4.0,
        ransac_iterations: int = 100,
        min_init_points: int = 100,
        min_inliers: int = 20,
        kf_translation_m: float = 0.06,
        kf_rotation_deg: float = 6.0,
        kf_min_overlap: float = 0.3,
        n_local_keyframes: int = 8,
        n_recent_keyframes: int = 2,
        cull_min_visible: int = 12,
        cull_min_found_ratio: float = 0.2,
        fuse_depth: bool = True,
        local_ba: bool = True,
        ba_window: int = 5,
        ba_fixed: int = 6,
        ba_iterations: int = 3,
        ba_max_points: int = 800,
        ba_inv_depth_sigma: float = 0.01,
        global_ba_keyframes: int = 500,
        global_ba_iterations: int = 10,
        loop_closing: bool = True,
        loop_min_gap: int = 10,
        loop_min_votes: int = 40,
        loop_min_inliers: int = 40,
        loop_min_correction_m: float = 0.02,
        loop_min_correction_deg: float = 1.0,
        loop_max_correction_m: float = 2.0,
        loop_max_correction_deg: float = 45.0,
        relocalise: bool = True,
        background: bool = False,
        vocabulary=None,
        bow_candidates: int = 10,
        readout_s: float = 0.0,
    ) -> None:
        if n_features < 50:
            raise TrackingError(f"n_features={n_features}: need at least 50 features to track")
        if not 0.0 < min_depth_m < max_depth_m:
            raise TrackingError(f"depth range [{min_depth_m}, {max_depth_m}] m is empty")
        if min_inliers < 6:
            raise TrackingError(f"min_inliers={min_inliers}: a pose needs at least 6 inliers")
        if n_local_keyframes < 1 or n_recent_keyframes < 1:
            raise TrackingError("n_local_keyframes and n_recent_keyframes must be at least 1")
        if not 0.0 < match_ratio <= 1.0:
            raise TrackingError(f"match_ratio={match_ratio}: must be in (0, 1]")
        if ba_window < 1 or ba_fixed < 0 or ba_iterations < 1 or global_ba_keyframes < 0:
            raise TrackingError("ba_window and ba_iterations must be at least 1, ba_fixed and global_ba_keyframes "
                                "at least 0")
        if not 0.0 <= readout_s <= 0.1:
            raise TrackingError(f"readout_s={readout_s}: a rolling shutter's readout time is 0 to 0.1 s")
        if loop_min_gap < 1 or loop_min_inliers < 6:
            raise TrackingError("loop_min_gap must be at least 1 and loop_min_inliers at least 6")
        self._extractor = OrbExtractor(
            n_features=n_features,
            grid_cols=grid_cols,
            grid_rows=grid_rows,
            fast_threshold=fast_threshold,
            min_fast_threshold=min_fast_threshold,
            n_levels=n_levels,
            scale_factor=scale_factor,
        )
        self._scale_factor = scale_factor
        self._min_depth = min_depth_m
        self._max_depth = max_depth_m
        self._max_new_depth = max_new_point_depth_m
        self._edge_spread = depth_edge_spread
        self._inv_depth_sigma = inv_depth_sigma
        self._search_radius = search_radius_px
        self._refine_radius = refine_radius_px
        self._max_hamming = max_hamming
        self._ratio = match_ratio
        self._confident_ratio = confident_ratio
        self._ransac_px = ransac_reproj_px
        self._ransac_iters = ransac_iterations
        self._min_init = min_init_points
        self._min_inliers = min_inliers
        self._kf_trans = kf_translation_m
        self._kf_rot = math.radians(kf_rotation_deg)
        self._kf_overlap = kf_min_overlap
        self._n_local_kf = n_local_keyframes
        self._n_recent_kf = n_recent_keyframes
        self._cull_visible = cull_min_visible
        self._cull_ratio = cull_min_found_ratio
        self._fuse = fuse_depth
        self._local_ba = local_ba
        self._ba_window = ba_window
        self._ba_fixed = ba_fixed
        self._ba_iterations = ba_iterations
        self._ba_max_point_move = 0.05
        self._ba_max_points = ba_max_points
        self._ba_inv_depth_sigma = ba_inv_depth_sigma
        self._global_ba_keyframes = global_ba_keyframes
        self._global_ba_iterations = global_ba_iterations
        self._loop_closing = loop_closing
        self._loop_gap = loop_min_gap
        self._loop_votes = loop_min_votes
        self._loop_inliers = loop_min_inliers
        self._loop_min_m = loop_min_correction_m
        self._loop_min_rad = math.radians(loop_min_correction_deg)
        self._loop_max_m = loop_max_correction_m
        self._loop_max_rad = math.radians(loop_max_correction_deg)
        self._relocalise = relocalise
        self._readout_s = readout_s
        # with a vocabulary (tracker.vocab.Vocabulary), loop and relocalisation candidates come from
        # a bag-of-words index (the best `bow_candidates`), else every keyframe is a candidate
        from octolog.tracker.places import BowIndex

        self._bow = BowIndex(vocabulary) if vocabulary is not None else None
        self._bow_top = bow_candidates
        # The back end (local BA, loop closing) for keyframe k starts when k is inserted and its
        # result is applied when keyframe k+1 is inserted (or at `finish`): a fixed point in the
        # frame sequence, so running it in a worker process cannot change any output.
        # A worker process, not a thread: gtsam holds the GIL while it optimises, which stalled the
        # tracking thread for tens of milliseconds at every keyframe.
        self._executor = Worker() if background else None
        self._pending: Worker | _BackendResult | None = None
        self._loop_edges: list[tuple[int, int, np.ndarray]] = []
        self._last_loop_kf = -(10**9)
        self._loop_candidate: tuple[int, np.ndarray | None] = (-1, None)
        # per tracked frame: (stamp, reference keyframe id, reference_from_camera)
        self._frames: list[tuple[int, int, np.ndarray]] = []
        self._last_pts = np.zeros((0, 2))
        self._last_kp_state = np.zeros(0, np.uint8)
        self._last_local = np.zeros(0, np.int64)
        self.loops: list[tuple[int, int]] = []  # (new, old) keyframe ids of closed loops

        self._intrinsics: Intrinsics | None = None
        self._undistort: Undistorter | None = None
        self._map = _MapPoints()
        self._keyframes: list[_Keyframe] = []
        self._kf_pos = np.zeros((0, 3))
        self._kf_axis = np.zeros((0, 3))
        self._last_pose: np.ndarray | None = None  # world_from_camera of the previous frame
        self._last_stamp = 0
        self._last_ok = False
        self._last_tracked_pose: np.ndarray | None = None
        self._last_inlier_ids = np.zeros(0, np.int64)  # map points matched by the previous frame
        self._velocity: tuple[np.ndarray, np.ndarray, int] | None = None  # rotvec, trans, dt_ns

    # -- public ---------------------------------------------------------------------------------

    def keypoints(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (raw, as in the image) of the last frame's keypoints and their state: KP_UNMATCHED,
        KP_OUTLIER (matched, rejected by the pose), KP_TRACKED (inlier) or KP_NEW (new map point)."""
        return self._last_pts, self._last_kp_state

    def local_map(self) -> np.ndarray:
        """World positions of the local map points the last frame was matched against."""
        ids = self._last_local[~self._map.bad[self._last_local]]
        return self._map.xyz[ids].copy()

    @property
    def n_keyframes(self) -> int:
        return len(self._keyframes)

    @property
    def n_map_points(self) -> int:
        return self._map.size

    def track(self, frame: RgbdFrame) -> TrackResult:
        """Estimate world_from_camera of `frame`; never raises for bad image content."""
        gray = self._check_frame(frame)
        feats = self._features(frame, gray)
        if not self._keyframes:
            return self._try_initialise(frame, feats)

        predicted = self._predict(frame.stamp_ns)
        relocalised = False
        try:
            tracked = self._track_against_map(feats, predicted, frame.stamp_ns)
            if tracked is None and self._relocalise:
                guess = self._relocalisation_guess(feats)
                if guess is not None:
                    tracked = self._track_against_map(feats, guess, frame.stamp_ns)
                    relocalised = tracked is not None
        except (cv2.error, np.linalg.LinAlgError):
            # Degenerate geometry inside OpenCV or a singular system: this frame is untrackable,
            # the stream is not broken.
            tracked = None
        if tracked is None:
            self._remember(frame.stamp_ns, predicted, ok=False)
            return TrackResult(frame.seq, frame.stamp_ns, predicted.copy(), STATE_LOST, False, -1, 0, 0)
        feats = tracked.feats
        pose = invert(tracked.camera_from_world)
        kf_id = -1
        corrected: dict[int, np.ndarray] = {}
        loop = None
        # A frame without enough depth adds no map points, so it must not replace the reference.
        if int(feats.has_depth.sum()) >= self._min_init and self._need_keyframe(pose, tracked):
            moved_map = self._pending is not None
            corrected, loop, pose = self._sync_backend(pose)
            if moved_map:
                # the map moved under this frame: re-fit its pose to the moved points it matched
                sol = self._solve(feats, tracked.kp_idx, tracked.map_idx, invert(pose), use_ransac=False)
                if sol is not None:
                    pose = invert(sol[0])
            kf_id = self._insert_keyframe(frame.seq, pose, feats, tracked)
            self._submit_backend()
        ref = self._keyframes[-1]
        self._frames.append((frame.stamp_ns, ref.id, invert(ref.world_from_camera) @ pose))
        self._remember(frame.stamp_ns, pose, ok=True)
        return TrackResult(
            frame.seq, frame.stamp_ns, pose.copy(), STATE_OK, kf_id >= 0, kf_id, tracked.n_matches, tracked.n_inliers,
            corrected, loop, relocalised, tracked.residual,
        )

    def trajectory(self) -> tuple[list[int], list[np.ndarray]]:
        """Stamps and world_from_camera of every tracked frame, re-expressed through the current pose
        of the keyframe it was tracked against (so back-end corrections reach every frame)."""
        kfs = self._keyframes
        return [s for s, _, _ in self._frames], [kfs[k].world_from_camera @ T for _, k, T in self._frames]

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return {kf.id: kf.world_from_camera.copy() for kf in self._keyframes}

    def finish(self) -> dict[int, np.ndarray]:
        """Wait for the back end and apply its last result; returns the keyframe poses it moved."""
        before = self.keyframe_poses()
        self._sync_backend(np.eye(4))
        if self._global_ba_keyframes > 0 and self._local_ba and len(self._keyframes) >= 2:
            # a last bundle adjustment, as ORB-SLAM runs after a loop: the trajectory and map that
            # are written out get the whole map's support. Over every keyframe (the first one fixed)
            # up to `global_ba_keyframes`; beyond, over the newest that many with the keyframes that
            # created their points held, so its time and memory stay bounded on long sessions
            window_n = min(len(self._keyframes), self._global_ba_keyframes)
            job = self._backend_job(window_n=window_n, max_points=None, loop_closing=False)
            self._pending = _run_backend(dataclasses.replace(job, iterations=self._global_ba_iterations))
            self._sync_backend(np.eye(4))
        if self._executor is not None:
            self._executor.close()
            self._executor = None
        after = self.keyframe_poses()
        return {i: T for i, T in after.items() if not np.array_equal(T, before[i])}

    # -- input ----------------------------------------------------------------------------------

    def _check_frame(self, frame: RgbdFrame) -> np.ndarray:
        """Grey image of the frame; TrackingError when the frame cannot match its intrinsics."""
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
        if intr != self._intrinsics:
            if self._intrinsics is not None and self._keyframes:
                raise TrackingError(f"frame {frame.seq}: intrinsics changed while tracking")
            self._intrinsics = intr
            self._undistort = Undistorter(intr)
        return rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)

    def _unroll(self, feats: FrameFeatures, step: tuple[np.ndarray, np.ndarray, int]) -> FrameFeatures:
        assert self._undistort is not None and self._intrinsics is not None
        return unroll_rolling_shutter(feats, self._last_pts[:, 1], self._intrinsics.height, self._undistort.K,
                                      self._readout_s, step)

    def _features(self, frame: RgbdFrame, gray: np.ndarray) -> FrameFeatures:
        assert self._undistort is not None
        pts, octave, desc = self._extractor.extract(gray)
        z = lookup_depth(
            frame.depth,
            frame.depth_scale_m,
            pts,
            min_depth_m=self._min_depth,
            max_depth_m=self._max_depth,
            max_spread=self._edge_spread,
        )
        uv = self._undistort(pts)
        self._last_pts = pts
        self._last_kp_state = np.zeros(len(pts), np.uint8)
        return FrameFeatures(uv=uv, octave=octave, desc=desc, z=z, xyz=backproject(uv, z, self._undistort.K))

    # -- motion model ---------------------------------------------------------------------------

    def _predict(self, stamp_ns: int) -> np.ndarray:
        """Constant-velocity prediction of world_from_camera, scaled to the frame interval."""
        assert self._last_pose is not None
        if self._velocity is None:
            return self._last_pose.copy()
        rotvec, trans, dt_ns = self._velocity
        dt_new = stamp_ns - self._last_stamp
        s = dt_new / dt_ns if dt_ns > 0 and dt_new > 0 else 1.0
        s = min(s, 4.0)  # a long gap is a stall, not a reason to extrapolate far
        step = np.eye(4)
        step[:3, :3] = so3_exp(rotvec * s)
        step[:3, 3] = trans * s
        return self._last_pose @ step

    def _remember(self, stamp_ns: int, pose: np.ndarray, *, ok: bool) -> None:
        if ok and self._last_ok and self._last_pose is not None:
            step = invert(self._last_pose) @ pose
            self._velocity = (so3_log(step[:3, :3]), step[:3, 3].copy(), stamp_ns - self._last_stamp)
        elif ok:
            # Recovered from LOST: the previous pose was a guess, so the velocity is unknown.
            self._velocity = None
        if ok:
            self._last_tracked_pose = pose.copy()
        self._last_pose = pose.copy()
        self._last_stamp = stamp_ns
        self._last_ok = ok

    # -- initialisation -------------------------------------------------------------------------

    def _try_initialise(self, frame: RgbdFrame, feats: FrameFeatures) -> TrackResult:
        pose = np.eye(4)
        if int(feats.has_depth.sum()) < self._min_init:
            return TrackResult(frame.seq, frame.stamp_ns, pose, STATE_LOST, False, -1, 0, 0)
        empty = np.zeros(0, np.int64)
        tracked = _Tracked(np.eye(4), empty, empty, 0, 0, feats)
        kf_id = self._insert_keyframe(frame.seq, pose, feats, tracked)
        self._frames.append((frame.stamp_ns, kf_id, np.eye(4)))
        self._remember(frame.stamp_ns, pose, ok=True)
        return TrackResult(frame.seq, frame.stamp_ns, pose.copy(), STATE_INIT, True, kf_id, 0, 0)

    # -- tracking -------------------------------------------------------------------------------

    def _local_keyframes(self, world_from_camera: np.ndarray, count: int) -> np.ndarray:
        """Sorted indices of the `count` keyframes nearest to a pose, always with the newest."""
        n_kf = len(self._keyframes)
        axis = world_from_camera[:3, 2]
        dist = np.linalg.norm(self._kf_pos - world_from_camera[:3, 3], axis=1)
        angle = np.arccos(np.clip(self._kf_axis @ axis, -1.0, 1.0))
        # 0.3 m per radian: roughly how far a move changes the view as much as a turn does.
        score = dist + 0.3 * angle
        score[max(0, n_kf - self._n_recent_kf) :] = -1.0
        return np.sort(np.lexsort((np.arange(n_kf), score))[:count])

    def _local_points(self, world_from_camera: np.ndarray) -> np.ndarray:
        """Sorted ids of good map points seen by the keyframes nearest to a pose plus the newest."""
        kfs = self._local_keyframes(world_from_camera, self._n_local_kf)
        ids = np.unique(np.concatenate([self._keyframes[i].point_ids for i in kfs]))
        return ids[~self._map.bad[ids]]

    def _project(self, ids: np.ndarray, camera_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projected pixels of map points and the mask of those in front of and inside the image."""
        assert self._intrinsics is not None
        intr = self._intrinsics
        p = self._map.xyz[ids] @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        z = p[:, 2]
        front = z > self._min_depth * 0.5
        zs = np.where(front, z, 1.0)
        uv = np.empty((ids.size, 2))
        uv[:, 0] = intr.fx * p[:, 0] / zs + intr.cx
        uv[:, 1] = intr.fy * p[:, 1] / zs + intr.cy
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
        return uv, inside

    def _guided(
        self, feats: FrameFeatures, ids: np.ndarray, camera_from_world: np.ndarray, radius: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keypoint idx, map id) matches of local points projected with a pose; also visible ids."""
        uv, inside = self._project(ids, camera_from_world)
        vis = ids[inside]
        mi, ki, _ = match_by_projection(
            uv[inside],
            self._map.desc[vis],
            feats.uv,
            feats.desc,
            radius=radius,
            max_distance=self._max_hamming,
            ratio=self._ratio,
        )
        return ki, vis[mi], vis

    def _confident(self, n_inliers: int, n_matches: int) -> bool:
        """Whether a pose has so many consistent matches that escalating cannot beat it."""
        return n_inliers >= 3 * self._min_inliers and n_inliers >= self._confident_ratio * n_matches

    def _solve(
        self, feats: FrameFeatures, kp_idx: np.ndarray, map_idx: np.ndarray, guess_cw: np.ndarray, use_ransac: bool,
        rounds: int = 3,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Pose (camera_from_world) and inlier mask from matches, or None when unreliable."""
        assert self._undistort is not None
        K = self._undistort.K
        if kp_idx.size < self._min_inliers:
            return None
        pts_w = self._map.xyz[map_idx]
        uv = feats.uv[kp_idx]
        init_inl = None
        guess = guess_cw
        if use_ransac:
            cv2.setRNGSeed(_RANSAC_SEED)
            try:
                ok, rvec, tvec, inl = cv2.solvePnPRansac(
                    pts_w.reshape(-1, 1, 3),
                    uv.reshape(-1, 1, 2),
                    K,
                    None,
                    iterationsCount=self._ransac_iters,
                    reprojectionError=self._ransac_px,
                    confidence=0.999,
                    flags=cv2.SOLVEPNP_EPNP,
                )
            except cv2.error:
                return None
            if not ok or inl is None or inl.size < self._min_inliers:
                return None
            guess = np.eye(4)
            guess[:3, :3] = cv2.Rodrigues(rvec)[0]
            guess[:3, 3] = tvec.ravel()
            init_inl = np.zeros(kp_idx.size, dtype=bool)
            init_inl[inl.ravel()] = True
        inv_sigma = self._scale_factor ** (-feats.octave[kp_idx].astype(np.float64))
        T, inl_mask = optimize_pose(
            guess,
            pts_w,
            uv,
            inv_sigma,
            feats.z[kp_idx],
            K,
            inv_depth_sigma=self._inv_depth_sigma,
            inliers=init_inl,
            rounds=rounds,
        )
        if int(inl_mask.sum()) < self._min_inliers or not np.all(np.isfinite(T)):
            return None
        return T, inl_mask

    def _track_against_map(self, raw: FrameFeatures, predicted_wc: np.ndarray, stamp_ns: int) -> _Tracked | None:
        """Match and estimate the pose; None when the frame cannot be tracked.

        With a rolling shutter the keypoints are moved to mid-readout twice: with the motion
        model's velocity for the first pose, then with the velocity from the previous frame to that
        pose (half a frame old instead of one and a half) for the second matching pass and the pose
        that is kept."""
        if len(raw) < self._min_inliers:
            return None
        rolling = self._readout_s > 0.0 and self._last_ok
        feats = self._unroll(raw, self._velocity) if rolling and self._velocity is not None else raw
        guess_cw = invert(predicted_wc)
        local = self._local_points(predicted_wc)

        # Escalate only while the answer is weak: a tight window around the prediction, a wide one,
        # then descriptor matching against the map around the last tracked pose (after LOST or a
        # jolt the prediction is useless, and that is where tracking resumes). Best inlier count wins.
        best: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None  # T, inl, ki, mi
        # The first window only searches for the points the previous frame matched: they are
        # known to be visible and distinctive, and a third of the local map is enough for a seed
        # pose at a third of the cost. The second pass below matches the whole local map.
        seed = self._last_inlier_ids if self._last_ok else np.zeros(0, np.int64)
        if seed.size < 3 * self._min_inliers:
            seed = local
        for attempt in range(3):
            if attempt < 2:
                radius = self._search_radius * (1.0 if attempt == 0 else 3.0)
                ki, mi, _ = self._guided(feats, seed if attempt == 0 else local, guess_cw, radius)
            else:
                assert self._last_tracked_pose is not None
                around = self._local_points(self._last_tracked_pose)
                q, tr, _ = match_brute_force(feats.desc, self._map.desc[around], max_distance=64, ratio=0.8)
                ki, mi = q, around[tr]
            # Behind a tracked frame the motion model's pose is a good start: a robust fit from it
            # needs no RANSAC (as ORB-SLAM's motion-model step); escalation brings RANSAC back.
            # This pose only seeds the tight second matching pass: two rounds suffice.
            trusted = attempt == 0 and self._last_ok and self._velocity is not None
            sol = self._solve(feats, ki, mi, guess_cw, use_ransac=not trusted, rounds=2)
            if sol is not None and (best is None or int(sol[1].sum()) > int(best[1].sum())):
                best = (sol[0], sol[1], ki, mi)
            if best is not None and self._confident(int(best[1].sum()), best[2].size):
                break
        if best is None:
            return None
        first = (best[0], best[1])
        ki, mi = best[2], best[3]
        if attempt > 0:
            local = self._local_points(invert(best[0]))
        T_cw, _ = first

        # Second pass: with a good pose, all local points can be matched in a tight window.
        feats2 = feats
        if rolling:
            assert self._last_pose is not None
            step = invert(self._last_pose) @ invert(T_cw)
            feats2 = self._unroll(raw, (so3_log(step[:3, :3]), step[:3, 3].copy(), stamp_ns - self._last_stamp))
        ki2, mi2, visible = self._guided(feats2, local, T_cw, self._refine_radius)
        second = self._solve(feats2, ki2, mi2, T_cw, use_ransac=False)
        if second is not None and int(second[1].sum()) >= int(first[1].sum()) // 2:
            T_cw, inl = second
            ki, mi = ki2, mi2
            feats = feats2
        else:
            inl = first[1]
        self._map.n_visible[visible] += 1
        self._map.n_found[mi[inl]] += 1
        self._last_inlier_ids = np.sort(mi[inl])
        self._last_kp_state[ki] = KP_OUTLIER
        self._last_kp_state[ki[inl]] = KP_TRACKED
        self._last_local = local
        ki, mi = ki[inl], mi[inl]
        uv, _ = self._project(mi, T_cw)
        scaled = (uv - feats.uv[ki]) * (self._scale_factor ** -feats.octave[ki].astype(np.float64))[:, None]
        residual = float(np.sqrt(np.mean(np.sum(scaled * scaled, axis=1)))) if ki.size else float("nan")
        return _Tracked(T_cw, ki, mi, int(inl.size), int(inl.sum()), feats, residual)

    # -- keyframes ------------------------------------------------------------------------------

    def _need_keyframe(self, pose: np.ndarray, tracked: _Tracked) -> bool:
        ref = self._keyframes[-1]
        rel = invert(ref.world_from_camera) @ pose
        if float(np.linalg.norm(rel[:3, 3])) > self._kf_trans or rotation_angle(rel[:3, :3]) > self._kf_rot:
            return True
        shared = int(np.isin(tracked.map_idx, ref.point_ids, assume_unique=True).sum())
        if ref.baseline_overlap < 0:
            ref.baseline_overlap = shared
        return shared < self._kf_overlap * ref.baseline_overlap

    def _insert_keyframe(self, seq: int, pose: np.ndarray, feats: FrameFeatures, tracked: _Tracked) -> int:
        """Add a keyframe: fuse depth into its matched points, create points for the rest."""
        mp = self._map
        R, t = pose[:3, :3], pose[:3, 3]
        z = feats.z
        # Information of a depth reading: Kinect-type noise grows with the square of the depth.
        weight_of = lambda zz: 1.0 / (zz * zz) ** 2  # noqa: E731

        kp_m, ids_m = tracked.kp_idx, tracked.map_idx
        with_d = z[kp_m] > 0.0
        if self._fuse and np.any(with_d):
            k, ids = kp_m[with_d], ids_m[with_d]
            obs = feats.xyz[k] @ R.T + t
            w_new = weight_of(z[k])
            w_old = mp.weight[ids]
            mp.xyz[ids] = (mp.xyz[ids] * w_old[:, None] + obs * w_new[:, None]) / (w_old + w_new)[:, None]
            mp.weight[ids] = w_old + w_new
        # The newest appearance matches the next frames best.
        mp.desc[ids_m] = feats.desc[kp_m]
        mp.n_obs[ids_m] += 1

        kf_id = len(self._keyframes)
        fresh = np.ones(len(feats), dtype=bool)
        fresh[kp_m] = False
        fresh &= (z > 0.0) & (z <= self._max_new_depth)
        k = np.flatnonzero(fresh)
        new_ids = mp.add(feats.xyz[k] @ R.T + t, feats.desc[k], weight_of(z[k]), kf_id)
        if self._last_kp_state.size == len(feats):
            self._last_kp_state[k] = KP_NEW

        # Retire points that are seen in view but rarely matched: likely bad depth or repeats.
        n = mp.size
        bad = (mp.n_visible[:n] >= self._cull_visible) & (
            mp.n_found[:n] < self._cull_ratio * mp.n_visible[:n]
        )
        mp.bad[:n] |= bad & (mp.n_obs[:n] < 3)

        point_ids = np.unique(np.concatenate([ids_m, new_ids]))
        shared = np.bincount(mp.ref_kf[ids_m], minlength=kf_id) if ids_m.size else np.zeros(kf_id, np.int64)
        covis = [int(j) for j in np.lexsort((np.arange(shared.size), -shared))[:3] if shared[j] >= 30]
        if self._bow is not None:
            self._bow.add(kf_id, feats.desc)
        self._keyframes.append(_Keyframe(kf_id, seq, pose.copy(), point_ids, feats,
                                         np.concatenate([kp_m, k]), np.concatenate([ids_m, new_ids]), sorted(covis)))
        self._kf_pos = np.vstack([self._kf_pos, t[None, :]])
        self._kf_axis = np.vstack([self._kf_axis, R[:, 2][None, :]])
        return kf_id

    # -- relocalisation -------------------------------------------------------------------------

    def _relocalisation_guess(self, feats: FrameFeatures) -> np.ndarray | None:
        """world_from_camera of a lost frame from a place match against every keyframe, or None."""
        from octolog.tracker.places import verify, vote

        if int(feats.has_depth.sum()) < self._min_inliers or not self._keyframes:
            return None
        cands = np.arange(len(self._keyframes))
        if self._bow is not None:
            cands, _ = self._bow.query(feats.desc, top=self._bow_top)
        scores = vote(feats, [self._keyframes[c].feats for c in cands])
        order = np.lexsort((cands, -scores))
        for o in order[:3]:
            if scores[o] < self._min_inliers:
                break
            c = int(cands[o])
            m = verify(feats, self._keyframes[c].feats, c, min_inliers=self._min_inliers,
                       refine=self._refine_args())
            if m is not None:
                return self._keyframes[c].world_from_camera @ m.T_kf_query
        return None

    # -- back end: local bundle adjustment and loop closing --------------------------------------

    def _refine_args(self) -> tuple[np.ndarray, float, float]:
        assert self._undistort is not None
        return self._undistort.K, self._scale_factor, self._inv_depth_sigma

    def _submit_backend(self) -> None:
        """Start the back end for the newest keyframe (in the worker process when there is one)."""
        if not (self._local_ba or self._loop_closing):
            return
        job = self._backend_job(window_n=self._ba_window, max_points=self._ba_max_points,
                                loop_closing=self._loop_closing)
        self._pending = self._executor.submit(job) if self._executor else _run_backend(job)

    def _sync_backend(self, pose: np.ndarray) -> tuple[dict[int, np.ndarray], tuple[int, int] | None, np.ndarray]:
        """Apply the pending back-end result; returns (moved keyframes if a loop closed, the loop,
        `pose` moved with the newest keyframe)."""
        res = self._pending
        if res is None:
            return {}, None, pose
        self._pending = None
        if not isinstance(res, _BackendResult):
            res = res.result()
        ref = self._keyframes[res.kf_id]
        old_ref = ref.world_from_camera.copy()
        for i, T in res.poses.items():
            kf = self._keyframes[i]
            kf.world_from_camera = T
            self._kf_pos[i] = T[:3, 3]
            self._kf_axis[i] = T[:3, 2]
        if res.loop is None and res.point_ids.size:
            # a point that local BA moved far was badly observed: retire it rather than trust it
            jump = np.linalg.norm(res.points - self._map.xyz[res.point_ids], axis=1) > self._ba_max_point_move
            self._map.bad[res.point_ids[jump]] = True
            self._map.xyz[res.point_ids[~jump]] = res.points[~jump]
        else:
            self._map.xyz[res.point_ids] = res.points
        delta = ref.world_from_camera @ invert(old_ref)
        for name in ("_last_pose", "_last_tracked_pose"):
            if getattr(self, name) is not None:
                setattr(self, name, delta @ getattr(self, name))
        self._loop_candidate = (res.kf_id, res.candidate) if res.candidate is not None else (-1, None)
        if res.loop is None:
            return {}, None, delta @ pose
        self._loop_edges.append(res.loop_edge)
        self.loops.append(res.loop)
        self._last_loop_kf = res.loop[0]
        return dict(res.poses), res.loop, delta @ pose

    def _backend_job(self, *, window_n: int, max_points: int | None, loop_closing: bool) -> _BackendJob:
        """A self-contained snapshot for the back end of the newest keyframe: BA over the newest
        `window_n` keyframes with at most `max_points` points (None: all), and loop detection if
        `loop_closing`."""
        mp, kfs = self._map, self._keyframes
        new = kfs[-1]
        n_kf = len(kfs)
        ba = None
        ba_kf = np.zeros(0, np.int64)
        ba_pids = np.zeros(0, np.int64)
        if self._local_ba and n_kf >= 2:
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
            fixed = np.sort(order[: self._ba_fixed][counts[order[: self._ba_fixed]] > 0])
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
                sig.append(self._scale_factor ** kf.feats.octave[kp].astype(np.float64))
            assert self._undistort is not None
            K = self._undistort.K
            ba = BundleProblem(
                poses_wc=np.stack([kfs[i].world_from_camera for i in ba_kf]),
                # as ORB-SLAM3 does: with fewer than two fixed neighbours (a new area) the oldest
                # window keyframe is held too, or the window would be free to drift as a whole
                fixed=np.array([i < window[0] or i == 0 or (fixed.size < 2 and i == window[0]) for i in ba_kf]),
                points=mp.xyz[pids].copy(),
                obs_kf=np.concatenate(kf_idx), obs_pt=np.concatenate(pt_idx), obs_uv=np.concatenate(uv),
                obs_z=np.concatenate(zz), obs_sigma=np.concatenate(sig),
                K=(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])),
                bf=1.0 / self._ba_inv_depth_sigma,
            )
            ba_pids = pids
        candidates = np.zeros(0, np.int64)
        if loop_closing and new.id - self._last_loop_kf > self._loop_gap:
            # old keyframes that share (almost) no map points with the new one: a match with one
            # of them is a place seen again after the map lost track of it
            shared = np.bincount(mp.ref_kf[new.point_ids], minlength=n_kf)
            candidates = np.flatnonzero((np.arange(n_kf) <= new.id - self._loop_gap) & (shared < 10))
            if self._bow is not None and candidates.size:
                candidates = np.sort(self._bow.query(new.feats.desc, top=self._bow_top, allowed=candidates)[0])
        return _BackendJob(
            kf_id=new.id, poses_wc=np.stack([kf.world_from_camera for kf in kfs]), ba=ba, ba_kf=ba_kf,
            ba_point_ids=ba_pids, iterations=self._ba_iterations, candidates=candidates,
            new_feats=new.feats, cand_feats=[kfs[i].feats for i in candidates],
            covis=[(i, j) for i in range(1, n_kf) for j in kfs[i].covis], loop_edges=list(self._loop_edges),
            # every map point and its creator: only a loop correction moves them all
            xyz=mp.xyz[: mp.size].copy() if candidates.size else None,
            ref_kf=mp.ref_kf[: mp.size].copy() if candidates.size else None,
            min_votes=self._loop_votes, min_inliers=self._loop_inliers, min_m=self._loop_min_m,
            min_rad=self._loop_min_rad, max_m=self._loop_max_m, max_rad=self._loop_max_rad,
            refine=self._refine_args(),
            previous_candidate=self._loop_candidate[1] if self._loop_candidate[0] == new.id - 1 else None,
            consistency_m=0.03, consistency_rad=math.radians(1.0),
        )


@dataclass
class _BackendJob:
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


@dataclass
class _BackendResult:
    kf_id: int
    poses: dict[int, np.ndarray]  # moved keyframes
    point_ids: np.ndarray
    points: np.ndarray
    loop: tuple[int, int] | None = None
    loop_edge: tuple[int, int, np.ndarray] | None = None
    candidate: np.ndarray | None = None  # world correction asked by an unconfirmed loop


def _run_backend(job: _BackendJob) -> _BackendResult:
    """Local BA around the newest keyframe, then loop detection and pose-graph correction.

    A step that fails numerically (gtsam's indeterminate system, degenerate geometry) is skipped:
    the back end improves the map when it can and never stops tracking. Failures depend only on
    the input, so skipping stays deterministic.
    """
    try:
        return _backend(job)
    except (RuntimeError, np.linalg.LinAlgError, cv2.error):
        if job.ba is None:
            return _BackendResult(job.kf_id, {}, job.ba_point_ids, np.zeros((0, 3)))
        try:
            return _backend(dataclasses.replace(job, candidates=np.zeros(0, np.int64), cand_feats=[]))
        except (RuntimeError, np.linalg.LinAlgError, cv2.error):
            return _BackendResult(job.kf_id, {}, np.zeros(0, np.int64), np.zeros((0, 3)))


def _backend(job: _BackendJob) -> _BackendResult:
    from octolog.tracker.places import verify, vote

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
        return _BackendResult(job.kf_id, moved, point_ids, points)

    scores = vote(job.new_feats, job.cand_feats)
    order = np.lexsort((job.candidates, -scores))
    match = None
    for c in order[:3]:
        if scores[c] < job.min_votes:
            break
        match = verify(job.new_feats, job.cand_feats[c], int(job.candidates[c]), min_inliers=job.min_inliers,
                       refine=job.refine)
        if match is not None:
            break
    if match is None:
        return _BackendResult(job.kf_id, moved, point_ids, points)
    old, new = match.keyframe, job.kf_id
    measured = match.T_kf_query  # old_from_new
    err = invert(invert(poses[old]) @ poses[new]) @ measured
    err_m, err_rad = float(np.linalg.norm(err[:3, 3])), rotation_angle(err[:3, :3])
    if err_m < job.min_m and err_rad < job.min_rad:
        return _BackendResult(job.kf_id, moved, point_ids, points)  # the map already agrees
    if err_m > job.max_m or err_rad > job.max_rad:
        return _BackendResult(job.kf_id, moved, point_ids, points)  # more than drift can explain
    # The correction this loop asks for, as a world-frame transform. A loop is closed only when
    # two consecutive keyframes ask for the same correction (as ORB-SLAM demands consistent
    # candidates): a single look-alike place cannot bend the map.
    C = poses[old] @ measured @ invert(poses[new])
    prev = job.previous_candidate
    if prev is None:
        return _BackendResult(job.kf_id, moved, point_ids, points, candidate=C)
    here = poses[new][:3, 3]
    d = invert(prev) @ C
    if float(np.linalg.norm(C[:3, :3] @ here + C[:3, 3] - (prev[:3, :3] @ here + prev[:3, 3]))) > job.consistency_m \
            or rotation_angle(d[:3, :3]) > job.consistency_rad:
        return _BackendResult(job.kf_id, moved, point_ids, points, candidate=C)
    rel = lambda i, j: invert(poses[i]) @ poses[j]  # noqa: E731
    edges = [(i - 1, i, rel(i - 1, i), 1.0) for i in range(1, len(poses))]
    edges += [(j, i, rel(j, i), 1.0) for i, j in job.covis]
    edges += [(i, j, T, 1.0) for i, j, T in job.loop_edges]
    edges.append((old, new, measured, 1.0))
    corrected = optimize_pose_graph(poses, edges, fixed=0)
    delta = corrected @ np.stack([invert(T) for T in poses])
    assert job.xyz is not None and job.ref_kf is not None
    xyz = job.xyz.copy()
    xyz[point_ids] = points
    d = delta[job.ref_kf]
    xyz = np.einsum("nij,nj->ni", d[:, :3, :3], xyz) + d[:, :3, 3]
    return _BackendResult(job.kf_id, {i: corrected[i] for i in range(len(poses))}, np.arange(xyz.shape[0]), xyz,
                          (new, old), (old, new, measured))
