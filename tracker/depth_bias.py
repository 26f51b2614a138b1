"""The depth camera's systematic error, measured from a session's own map.

A stereo or structured-light camera measures disparity d = f b / z; a per-unit calibration error
leaves an offset in it, so every reading is off by about z^2 offset / (f b): a bias growing with
the square of the range, unlike the noise, which averages out. In inverse depth it is one constant,
`inverse_offset` (1/m): 1/z_true = 1/z_read - inverse_offset (> 0: the camera reads short, by
inverse_offset * z^2 metres at z).

The map has many points seen from several keyframes at different ranges. Each depth reading puts
its point at R_k z_true ray + t_k; with the first-order correction z_true = z + inverse_offset z^2,
and the keyframes' translations off by one common factor (the scale the biased depth gave the
trajectory), the point's position from every reading is linear in (inverse_offset, scale). Both
come from one weighted least-squares fit over every point seen with depth at least twice, the
points' positions eliminated in closed form, outlying readings down-weighted (Huber, iterated).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# readings of at least this many points, seen with depth from two keyframes or more, make an estimate
MIN_POINTS = 200
# a reading's residual beyond this many times the median residual is down-weighted (Huber)
HUBER_MEDIANS = 3.0
IRLS_ROUNDS = 4
# the ranges the report gives the bias at (m)
REPORT_RANGES_M = (1.0, 2.0, 3.0, 4.0, 5.0)


@dataclass(frozen=True)
class DepthBias:
    """What the map says of the camera's depth: `inverse_offset` (1/m, see the module) and its
    standard error, the trajectory scale fitted with it, and the bias at `REPORT_RANGES_M`."""

    inverse_offset: float
    sigma: float
    scale: float
    points: int
    readings: int
    bias_m: dict[float, float] = field(default_factory=dict)  # range -> reading minus truth (m; < 0: short)

    @property
    def confident(self) -> bool:
        """The offset is at least three standard errors from zero."""
        return abs(self.inverse_offset) >= 3.0 * self.sigma

    def summary(self) -> str:
        """One line: how far the camera's depth is off at a few ranges."""
        at = ", ".join(f"{-100 * b / z:+.2f} % at {z:g} m" for z, b in self.bias_m.items())
        verdict = "" if self.confident else " (not significant)"
        return (f"depth reads short by {at}{verdict}; inverse offset {self.inverse_offset:.5f} ± {self.sigma:.5f} 1/m "
                f"from {self.points} points seen at least twice")

    def as_dict(self) -> dict:
        return {"inverse_offset_per_m": self.inverse_offset, "sigma_per_m": self.sigma, "scale": self.scale,
                "points": self.points, "readings": self.readings, "confident": self.confident,
                "bias_m": {f"{z:g}": b for z, b in self.bias_m.items()}}


def estimate_depth_bias(rotations: np.ndarray, translations: np.ndarray, kf_index: np.ndarray, point_id: np.ndarray,
                        xyz_cam: np.ndarray, z_map: np.ndarray) -> DepthBias | None:
    """The bias from depth readings: reading i is keyframe `kf_index[i]` (world_from_camera rotation
    `rotations[k]`, translation `translations[k]`) seeing point `point_id[i]` at `xyz_cam[i]` (its
    raw depth times the pixel's ray), where the map has the point at depth `z_map[i]`. The
    correction's regressor takes the map's depth, not the reading: a noisy reading in both sides of
    the fit would bias it (errors in variables). None with fewer than MIN_POINTS points seen twice."""
    z = xyz_cam[:, 2]
    ok = (z > 0) & (z_map > 0)
    kf_index, point_id, xyz_cam, z, z_map = kf_index[ok], point_id[ok], xyz_cam[ok], z[ok], z_map[ok]
    _, inverse, counts = np.unique(point_id, return_inverse=True, return_counts=True)
    keep = counts[inverse] >= 2
    if int((counts >= 2).sum()) < MIN_POINTS:
        return None
    kf_index, xyz_cam, z, z_map = kf_index[keep], xyz_cam[keep], z[keep], z_map[keep]
    _, group = np.unique(point_id[keep], return_inverse=True)
    R = rotations[kf_index]
    a = np.einsum("nij,nj->ni", R, xyz_cam)  # the reading's point, rotated into the world
    b = a * (z_map * z_map / z)[:, None]  # what one unit of inverse offset moves it by: ray z^2
    z = z_map
    t = translations[kf_index]
    w = 1.0 / z ** 4  # depth noise grows with z^2
    for _ in range(IRLS_ROUNDS):
        y, A = _centred(a, b, t, w, group)
        W = np.repeat(w, 3)
        Aw = A * W[:, None]
        N = A.T @ Aw
        x = np.linalg.solve(N, Aw.T @ y)
        r = np.linalg.norm((y - A @ x).reshape(-1, 3), axis=1) * np.sqrt(w)
        k = HUBER_MEDIANS * float(np.median(r))
        w = (1.0 / z ** 4) * np.minimum(1.0, k / np.maximum(r, 1e-12))
    dof = max(A.shape[0] - 2 - 3 * int(group.max() + 1), 1)
    s2 = float(np.sum(W * (y - A @ x) ** 2)) / dof
    cov = s2 * np.linalg.inv(N)
    beta, scale = float(x[0]), float(x[1])
    bias = {zr: float(zr / (1.0 + beta * zr) - zr) for zr in REPORT_RANGES_M}  # reading at true range zr
    return DepthBias(beta, float(np.sqrt(cov[0, 0])), scale, int((counts >= 2).sum()), int(keep.sum()), bias)


def bias_from_map(keyframes: Sequence[Any], points_xyz: np.ndarray) -> DepthBias | None:
    """The estimate from a tracker's map: its keyframes (`world_from_camera`, `feats.xyz` the raw
    readings, `obs_kp` / `obs_pid` which keypoint sees which point) and its points' positions."""
    kfs = [kf for kf in keyframes if kf.obs_kp.size]
    if len(kfs) < 2:
        return None
    poses = np.array([kf.world_from_camera for kf in kfs])
    kf_index = np.concatenate([np.full(kf.obs_kp.size, i) for i, kf in enumerate(kfs)])
    xyz = np.concatenate([kf.feats.xyz[kf.obs_kp] for kf in kfs])
    pid = np.concatenate([kf.obs_pid for kf in kfs])
    R, t = poses[kf_index, :3, :3], poses[kf_index, :3, 3]
    z_map = np.einsum("ni,ni->n", R[:, :, 2], points_xyz[pid] - t)  # the point's depth in the keyframe
    return estimate_depth_bias(poses[:, :3, :3], poses[:, :3, 3], kf_index, pid, xyz, z_map)


def _centred(a: np.ndarray, b: np.ndarray, t: np.ndarray, w: np.ndarray, group: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """The fit's rows with each point's position eliminated: its weighted mean over its readings
    subtracted from every column (y = a - mean a; A = [mean b - b, mean t - t]), three rows a reading."""
    n_groups = int(group.max()) + 1
    wsum = np.bincount(group, w, n_groups)

    def centre(v: np.ndarray) -> np.ndarray:
        mean = np.stack([np.bincount(group, w * v[:, i], n_groups) for i in range(3)], axis=1) / wsum[:, None]
        return v - mean[group]

    y = centre(a).ravel()
    A = np.stack([-centre(b).ravel(), -centre(t).ravel()], axis=1)
    return y, A
