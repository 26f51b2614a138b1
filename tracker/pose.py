"""Camera pose maths of the tracker: SO(3) helpers, the robust pose-only fit, rolling-shutter unroll.

Plain numpy (no gtsam): the front end fits every frame's pose with `optimize_pose`, place
recognition refines a verified match with it, and the back end measures loop corrections with
`rotation_angle`. Deterministic: the same inputs give byte-identical outputs in any process.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from octolog.tracker.features import FrameFeatures

# Chi-square 95% quantiles for 2 (pixel) and 3 (pixel + inverse depth) degrees of freedom.
CHI2_2DOF = 5.991
CHI2_3DOF = 7.815


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


def _residual_fn(points_w: np.ndarray, uv: np.ndarray, inv_sigma_px: np.ndarray, inv_z_meas: np.ndarray,
                 dsig_d: np.ndarray, K: np.ndarray
                 ) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """optimize_pose's residuals at a pose: camera-frame points, weighted residuals, chi-square."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n = points_w.shape[0]

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

    return residuals


def _pose_jacobian(pa: np.ndarray, obs: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """The (3m, 6) Jacobian of the active observations' weighted residuals (rows u, v, inverse
    depth) at their camera-frame points `pa`; `obs` holds each one's sigma scale, Huber delta and
    inverse-depth factor."""
    m = pa.shape[0]
    x, y, z = pa[:, 0], pa[:, 1], pa[:, 2]
    s, nd = obs[:, 0], obs[:, 2]
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
    return J


def _gauss_newton_step(J: np.ndarray, r: np.ndarray, chi2: np.ndarray, idx: np.ndarray,
                       dh: np.ndarray, prior: tuple[np.ndarray, float] | None = None) -> np.ndarray | None:
    """One Huber-weighted Gauss-Newton step on the active observations `idx` (and the rotation
    prior: (log(R R_prior^T), 1/sigma²)); None if singular."""
    m = idx.size
    rr = np.take(r, idx, axis=1).ravel()
    e = np.sqrt(np.take(chi2, idx))
    w = np.minimum(dh / np.maximum(e, 1e-12), 1.0)  # Huber: 1 where e <= dh
    Jw = (J.reshape(3, m, 6) * w[:, None]).reshape(3 * m, 6)
    H = Jw.T @ J
    g = Jw.T @ rr
    if prior is not None:  # residual log(Exp(d) R R_prior^T) ~ e + d: identity Jacobian on rotation
        e, info = prior
        H[3:, 3:] += np.eye(3) * info
        g[3:] += e * info
    H.flat[::7] += 1e-9 + 1e-6 * H.diagonal()
    try:
        return -np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return None


def _gauss_newton(R: np.ndarray, t: np.ndarray, active: np.ndarray, res: tuple | None,
                  residuals: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]],
                  per_obs: np.ndarray, fx: float, fy: float, iterations: int,
                  rotation_prior: tuple[np.ndarray, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One round of optimize_pose: up to `iterations` Gauss-Newton steps on the `active`
    observations, from `res` (the residuals at R, t when already computed)."""
    for _ in range(iterations):
        p, r, chi2 = residuals(R, t) if res is None else res
        res = None
        idx = np.flatnonzero(active & np.isfinite(chi2))
        m = idx.size
        if m < 6:
            break
        pa = np.take(p, idx, axis=0)
        obs = np.take(per_obs, idx, axis=0)
        J = _pose_jacobian(pa, obs, fx, fy)
        prior = None if rotation_prior is None else \
            (so3_log(R @ rotation_prior[0].T), 1.0 / rotation_prior[1] ** 2)
        dx = _gauss_newton_step(J, r, chi2, idx, obs[:, 1], prior)
        if dx is None:
            break
        dR = so3_exp(dx[3:])
        R = dR @ R
        t = dR @ t + dx[:3]
        if float(dx @ dx) < 1e-10:  # below 10 micrometres / microradians
            break
    return R, t


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
    rotation_prior: tuple[np.ndarray, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine camera_from_world on 3D-2D matches; returns the pose and the final inlier mask.

    Residuals are the reprojection error in units of the keypoint's pyramid-level sigma and, where
    the keypoint has a depth reading, the inverse-depth error in units of `inv_depth_sigma`
    (1/m), which constrains translation along the optical axis that pixels alone see poorly.
    Gauss-Newton with Huber weights runs `rounds` times; between rounds observations are
    re-classified by a chi-square test so a wrong match cannot pull the pose (the scheme of
    ORB-SLAM's pose-only optimisation). `rotation_prior` (camera_from_world's rotation as the gyro
    predicts it, its sigma in rad) adds that rotation as one more residual.
    """
    fx, fy = K[0, 0], K[1, 1]
    R = camera_from_world[:3, :3].copy()
    t = camera_from_world[:3, 3].copy()
    n = points_w.shape[0]
    has_d = z_meas > 0.0
    inv_z_meas = np.where(has_d, 1.0 / np.where(has_d, z_meas, 1.0), 0.0)
    dsig = 1.0 / inv_depth_sigma
    thr = np.where(has_d, CHI2_3DOF, CHI2_2DOF)
    delta_h = np.sqrt(thr)
    active = np.ones(n, dtype=bool) if inliers is None else inliers.copy()
    # Per-observation constants gathered once per iteration: sigma scale, Huber delta and the
    # inverse-depth Jacobian factor (-dsig with depth, +0 without).
    per_obs = np.stack([inv_sigma_px, delta_h, np.where(has_d, -dsig, 0.0)]).T.copy()
    dsig_d = np.where(has_d, dsig, 0.0)
    residuals = _residual_fn(points_w, uv, inv_sigma_px, inv_z_meas, dsig_d, K)

    res = None  # residuals at the current pose, when already computed
    for rnd in range(rounds):
        if int(active.sum()) < 6:
            break
        R, t = _gauss_newton(R, t, active, res, residuals, per_obs, fx, fy, iterations, rotation_prior)
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


def unsupported_jump(tracking: Any, predicted_wc: np.ndarray, pose_wc: np.ndarray, n_inliers: int, dt_ns: int) -> bool:
    """Whether a tracked pose leaves the motion model's prediction (both world_from_camera) by more
    than hand-held motion can (`tracking.max_jump_m`, `max_jump_deg` a frame at 30 fps, growing with
    the square of a longer interval `dt_ns`) on fewer inliers than `tracking.jump_support`: a jump
    the motion cannot explain, from too little evidence (the frame is LOST). For a prediction made
    from a tracked frame's velocity: after LOST it is a guess and judges nothing."""
    if n_inliers >= tracking.jump_support:
        return False
    frames = max(1.0, dt_ns * 30e-9) ** 2
    dev = np.linalg.inv(predicted_wc) @ pose_wc
    return float(np.linalg.norm(dev[:3, 3])) > tracking.max_jump_m * frames \
        or rotation_angle(dev[:3, :3]) > math.radians(tracking.max_jump_deg) * frames
