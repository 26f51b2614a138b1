"""Rolling-shutter model of the native tracker: keypoints moved to mid-readout, and where the
readout time comes from (the source's camera, or the config)."""

from __future__ import annotations

import numpy as np
import pytest

from octolog.kit.errors import ConfigError
from octolog.replay.sources import open_source
from octolog.tracker.config import TrackerConfig, for_source
from octolog.tracker.features import FrameFeatures
from octolog.tracker.pose import optimize_pose, so3_exp, unroll_rolling_shutter

H, W = 480, 640
K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
READOUT = 0.02
W_RAD = np.array([0.3, -0.6, 0.2])  # rad/s
V_MS = np.array([0.4, -0.3, 0.25])  # m/s, camera frame


def _scene(n: int = 400, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """World points in front of a camera at mid_wc, and that pose."""
    rng = np.random.default_rng(seed)
    mid_wc = np.eye(4)
    mid_wc[:3, :3] = so3_exp(np.array([0.05, -0.1, 0.02]))
    mid_wc[:3, 3] = [0.1, -0.05, 0.2]
    uv = rng.uniform([20, 20], [W - 20, H - 20], size=(n, 2))
    z = rng.uniform(0.8, 3.5, size=n)
    p_c = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z])
    return p_c @ mid_wc[:3, :3].T + mid_wc[:3, 3], mid_wc


def _project(p_c: np.ndarray) -> np.ndarray:
    return np.column_stack([K[0, 0] * p_c[:, 0] / p_c[:, 2] + K[0, 2], K[1, 1] * p_c[:, 1] / p_c[:, 2] + K[1, 2]])


def _rolling_capture(points_w: np.ndarray, mid_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point as a rolling shutter sees it: camera coordinates at its own row's time, and the row.

    The camera moves with constant twist (W_RAD, V_MS) about the mid-readout pose; a point's row
    and its capture time depend on each other, so iterate to the fixed point."""
    p_mid = (points_w - mid_wc[:3, 3]) @ mid_wc[:3, :3]
    rows = _project(p_mid)[:, 1]
    for _ in range(20):
        tau = (rows / H - 0.5) * READOUT
        # camera at tau: R_mid exp(tau w), t_mid + R_mid tau v  =>  p_tau = exp(-tau w) (p_mid - tau v)
        p_tau = np.stack([so3_exp(-t * W_RAD) @ (p - t * V_MS) for t, p in zip(tau, p_mid)])
        rows = _project(p_tau)[:, 1]
    return p_tau, rows


def _features(p_c: np.ndarray, with_depth: bool = True) -> FrameFeatures:
    n = p_c.shape[0]
    z = p_c[:, 2].copy() if with_depth else np.zeros(n)
    return FrameFeatures(uv=_project(p_c), octave=np.zeros(n, np.int32), desc=np.zeros((n, 32), np.uint8), z=z,
                         xyz=p_c.copy() if with_depth else np.zeros((n, 3)))


def _step(dt_s: float = 1 / 30) -> tuple[np.ndarray, np.ndarray, int]:
    return W_RAD * dt_s, V_MS * dt_s, round(dt_s * 1e9)


def test_unrolled_keypoints_land_where_a_global_shutter_at_mid_readout_sees_them() -> None:
    points_w, mid_wc = _scene()
    p_tau, rows = _rolling_capture(points_w, mid_wc)
    truth = _project((points_w - mid_wc[:3, 3]) @ mid_wc[:3, :3])
    raw = _features(p_tau)
    fixed = unroll_rolling_shutter(raw, rows, H, K, READOUT, _step())
    before = np.linalg.norm(raw.uv - truth, axis=1)
    after = np.linalg.norm(fixed.uv - truth, axis=1)
    assert before.max() > 2.0  # the shutter's smear is pixels at this speed
    assert after.max() < 0.05, after.max()  # what is left is second order in the row time
    z_truth = ((points_w - mid_wc[:3, 3]) @ mid_wc[:3, :3])[:, 2]
    assert np.abs(fixed.z - z_truth).max() < 1e-4
    # without depth only the rotation is undone: the translation's share stays, the rotation's goes
    rot_only = unroll_rolling_shutter(_features(p_tau, with_depth=False), rows, H, K, READOUT, _step())
    assert np.all(rot_only.z == 0.0)
    assert np.sqrt(np.mean((rot_only.uv - truth) ** 2)) < 0.5 * np.sqrt(np.mean((raw.uv - truth) ** 2))
    # a global shutter (readout 0) or no motion leaves the keypoints alone
    assert unroll_rolling_shutter(raw, rows, H, K, 0.0, _step()) is raw
    still = unroll_rolling_shutter(raw, rows, H, K, READOUT, (np.zeros(3), np.zeros(3), 33_000_000))
    np.testing.assert_allclose(still.uv, raw.uv, atol=1e-9)


def test_pose_from_unrolled_keypoints_is_the_mid_readout_pose() -> None:
    points_w, mid_wc = _scene()
    p_tau, rows = _rolling_capture(points_w, mid_wc)
    guess = np.linalg.inv(mid_wc)
    guess[:3, 3] += [0.01, -0.01, 0.02]  # a rough start, as the motion model gives

    def pose_error(feats: FrameFeatures) -> float:
        T_cw, inl = optimize_pose(guess, points_w, feats.uv, np.ones(len(feats)), feats.z, K, inv_depth_sigma=0.03)
        assert inl.mean() > 0.5
        return float(np.linalg.norm(np.linalg.inv(T_cw)[:3, 3] - mid_wc[:3, 3]))

    raw = _features(p_tau)
    err_raw = pose_error(raw)
    err_fixed = pose_error(unroll_rolling_shutter(raw, rows, H, K, READOUT, _step()))
    assert err_raw > 0.002, err_raw  # millimetres off when the shutter is ignored
    assert err_fixed < 0.0003, err_fixed
    assert err_fixed < err_raw / 10


def test_readout_comes_from_the_source_unless_configured(tmp_path) -> None:
    class Kinect:
        readout_s = 0.02

    class GlobalShutter:
        readout_s = 0.0

    assert for_source(TrackerConfig(), Kinect()).rolling_shutter_ms == pytest.approx(20.0)
    assert for_source(TrackerConfig(), GlobalShutter()).rolling_shutter_ms == 0.0
    assert for_source(TrackerConfig(rolling_shutter_ms=0.0), Kinect()).rolling_shutter_ms == 0.0
    assert for_source(TrackerConfig(rolling_shutter_ms=12.5), Kinect()).rolling_shutter_ms == 12.5

    # the TUM folder's name says which Kinect took it; only freiburg1's readout is measured
    for name, want in (("rgbd_dataset_freiburg1_desk", 0.02), ("rgbd_dataset_freiburg3_office", 0.0)):
        folder = tmp_path / name
        (folder / "rgb").mkdir(parents=True)
        (folder / "rgb.txt").write_text("1.0 rgb/a.png\n")
        (folder / "depth.txt").write_text("1.0 depth/a.png\n")
        assert open_source(f"tum:{folder}").readout_s == want


def test_bad_readout_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="rolling_shutter_ms"):
        TrackerConfig(rolling_shutter_ms=-1.0).validate()
    with pytest.raises(ConfigError, match="rolling_shutter_ms"):
        TrackerConfig(rolling_shutter_ms=250.0).validate()
    with pytest.raises(ConfigError, match="rolling_shutter_ms"):  # checked where the core's parameters are built
        TrackerConfig(rolling_shutter_ms=500.0).odometry_params()
    assert TrackerConfig(rolling_shutter_ms=20.0).odometry_params().readout_s == pytest.approx(0.02)
    assert TrackerConfig().odometry_params().readout_s == 0.0  # unset: a global shutter
