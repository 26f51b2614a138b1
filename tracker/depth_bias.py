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

The report also measures the offset band by band (each `REPORT_RANGES_M` ± half a metre with
enough readings): one more fit, with the final weights, where each band has its own offset, so a
camera whose error is not one disparity offset shows it. The bands share the one scale unknown: on
views at one range a depth offset and a trajectory scale look alike, so a bias confined to some
bands is partly seen in the others.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

# readings of at least this many points, seen with depth from two keyframes or more, make an estimate
MIN_POINTS = 200
# a reading's residual beyond this many times the median residual is down-weighted (Huber)
HUBER_MEDIANS = 3.0
IRLS_ROUNDS = 4
# the ranges the report gives the bias at (m), and the band of map depths measured for each: centre ± half a metre
REPORT_RANGES_M = (1.0, 2.0, 3.0, 4.0, 5.0)
BAND_HALF_WIDTH_M = 0.5
# a band is reported with at least this many readings in it
MIN_BAND_READINGS = 500


@dataclass(frozen=True)
class DepthBias:
    """What the map says of the camera's depth: `inverse_offset` (1/m, see the module) and its
    standard error, the trajectory scale fitted with it, and the offset measured on its own in each
    range band (`bands`: centre -> (offset, its standard error, readings)), where the map has the readings."""

    inverse_offset: float
    sigma: float
    scale: float
    points: int
    readings: int
    bands: dict[float, tuple[float, float, int]] = field(default_factory=dict)
    # the correction the readings had already taken (1/m: tracker.depth.inverse_offset plus what
    # tracker.depth.correct_bias added, `corrections` times); the camera's bias is both together
    corrected: float = 0.0
    corrections: int = 0
    fb: float = 0.0  # the camera's focal length times baseline (px m), when known: the bias in disparity

    def after(self, corrected: float, corrections: int, fb: float = 0.0) -> DepthBias:
        """This estimate, made from readings that had taken the correction `corrected`, of a camera
        with focal length times baseline `fb` (0: unknown)."""
        return replace(self, corrected=corrected, corrections=corrections, fb=fb)

    @property
    def disparity_px(self) -> float | None:
        """The camera's bias as a disparity offset (px; > 0: reads short), when its fb is known."""
        return (self.inverse_offset + self.corrected) * self.fb if self.fb else None

    @property
    def confident(self) -> bool:
        """The offset is at least three standard errors from zero."""
        return abs(self.inverse_offset) >= 3.0 * self.sigma

    @property
    def bias_m(self) -> dict[float, float]:
        """What the camera reads at each of `REPORT_RANGES_M`, minus the range (m; < 0: short), by the
        one-offset model."""
        return _bias_at(self.inverse_offset + self.corrected)

    @property
    def band_bias_m(self) -> dict[float, tuple[float, float]]:
        """The bias measured in each band, at its centre: (reading minus range, standard error), m."""
        return {z: (_bias_at(b + self.corrected, (z,))[z], z * z * s) for z, (b, s, _) in self.bands.items()}

    def summary(self) -> str:
        """One line: how far the camera's depth is off at the ranges the map measured it."""
        bands = self.band_bias_m
        at = ", ".join(f"{-100 * b / z:+.2f} ± {100 * s / z:.2f} % at {z:g} m" for z, (b, s) in bands.items()) if bands \
            else ", ".join(f"{-100 * b / z:+.2f} % at {z:g} m" for z, b in self.bias_m.items() if z in (2.0, 4.0))
        verdict = "" if self.confident else " (not significant)"
        done = (f"{self.corrected:.5f} 1/m corrected" + (f" ({self.corrections} times while tracking)"
                                                          if self.corrections else "") + ", ") if self.corrected else ""
        px = f" (a disparity offset of {self.disparity_px:+.3f} px)" if self.disparity_px is not None else ""
        return (f"depth reads short by {at}{px}; {done}inverse offset {self.inverse_offset:.5f} ± {self.sigma:.5f} 1/m "
                f"left{verdict}, from {self.points} points seen at least twice")

    def as_dict(self) -> dict:
        return {"inverse_offset_per_m": self.inverse_offset, "sigma_per_m": self.sigma, "scale": self.scale,
                "points": self.points, "readings": self.readings, "confident": self.confident,
                "bias_m": {f"{z:g}": b for z, b in self.bias_m.items()}, "corrected_per_m": self.corrected,
                "corrections": self.corrections, "disparity_offset_px": self.disparity_px,
                "bands": {f"{z:g}": {"bias_m": b, "sigma_m": sd, "readings": self.bands[z][2]}
                          for z, (b, sd) in self.band_bias_m.items()}}


def estimate_depth_bias(rotations: np.ndarray, translations: np.ndarray, kf_index: np.ndarray, point_id: np.ndarray,
                        xyz_cam: np.ndarray, z_map: np.ndarray) -> DepthBias | None:
    """The bias from depth readings: reading i is keyframe `kf_index[i]` (world_from_camera rotation
    `rotations[k]`, translation `translations[k]`) seeing point `point_id[i]` at `xyz_cam[i]` (its
    raw depth times the pixel's ray), where the map has the point at depth `z_map[i]`. The
    correction's regressor takes the map's depth, not the reading: a noisy reading in both sides of
    the fit would bias it (errors in variables). None with fewer than MIN_POINTS points seen twice.
    With the weights of the one-offset fit, one more fit gives each range band its own offset."""
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
    try:
        for _ in range(IRLS_ROUNDS):
            x, cov, r = _fit(a, [b], t, w, group)
            k = HUBER_MEDIANS * float(np.median(r))
            w = (1.0 / z ** 4) * np.minimum(1.0, k / np.maximum(r, 1e-12))
    except np.linalg.LinAlgError:  # degenerate views (one place, no baseline): nothing to say
        return None
    beta, sigma, scale = float(x[0]), float(np.sqrt(cov[0, 0])), float(x[1])
    centre = np.asarray(REPORT_RANGES_M)
    band = np.argmin(np.abs(z[:, None] - centre[None, :]), axis=1)
    inside = np.abs(z - centre[band]) < BAND_HALF_WIDTH_M
    counted = [(i, int(np.sum(inside & (band == i)))) for i in range(centre.size)]
    counted = [(i, n) for i, n in counted if n >= MIN_BAND_READINGS]
    bands: dict[float, tuple[float, float, int]] = {}
    if counted:
        # readings outside every reported band keep the one offset, so they still place their points
        rest = ~np.isin(band, [i for i, _ in counted]) | ~inside
        columns = [b * (inside & (band == i))[:, None] for i, _ in counted] + ([b * rest[:, None]] if rest.any() else [])
        try:
            xb, covb, _ = _fit(a, columns, t, w, group)
            bands = {float(centre[i]): (float(xb[j]), float(np.sqrt(covb[j, j])), n) for j, (i, n) in enumerate(counted)}
        except np.linalg.LinAlgError:  # a band the views cannot tell from the others: the one offset only
            bands = {}
    return DepthBias(beta, sigma, scale, int((counts >= 2).sum()), int(keep.sum()), bands)


def _fit(a: np.ndarray, offsets: list[np.ndarray], t: np.ndarray, w: np.ndarray, group: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least squares of the readings' points `a` moved by one offset per column of
    `offsets` and the translations `t` scaled, each point's position eliminated: (offsets then
    scale, their covariance, each reading's whitened residual norm)."""
    y, A = _centred(a, offsets + [t], w, group)
    W = np.repeat(w, 3)
    Aw = A * W[:, None]
    N = A.T @ Aw
    x = np.linalg.solve(N, Aw.T @ y)
    e = y - A @ x
    dof = max(A.shape[0] - A.shape[1] - 3 * int(group.max() + 1), 1)
    cov = float(np.sum(W * e ** 2)) / dof * np.linalg.inv(N)
    return x, cov, np.linalg.norm(e.reshape(-1, 3), axis=1) * np.sqrt(w)


def _bias_at(beta: float, ranges: tuple[float, ...] = REPORT_RANGES_M) -> dict[float, float]:
    """What a camera with the inverse-depth offset `beta` reads at each range, minus the range."""
    return {zr: float(zr / (1.0 + beta * zr) - zr) for zr in ranges}


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


def _centred(a: np.ndarray, columns: list[np.ndarray], w: np.ndarray, group: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """The fit's rows with each point's position eliminated: its weighted mean over its readings
    subtracted from every column (y = a - mean a; A = [mean c - c for each column]), three rows a reading."""
    n_groups = int(group.max()) + 1
    wsum = np.bincount(group, w, n_groups)

    def centre(v: np.ndarray) -> np.ndarray:
        mean = np.stack([np.bincount(group, w * v[:, i], n_groups) for i in range(3)], axis=1) / wsum[:, None]
        return v - mean[group]

    y = centre(a).ravel()
    A = np.stack([-centre(c).ravel() for c in columns], axis=1)
    return y, A
