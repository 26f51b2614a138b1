"""The depth camera's systematic error measured from a map (tracker/depth_bias.py), on readings made
here with a known offset, and the tracker's and the mapper's correction settings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from octolog.kit.errors import ConfigError
from octolog.kit import depthmodel
from octolog.replay.synthetic import SyntheticScene
from octolog.tracker.config import TrackerConfig, with_depth_model
from octolog.tracker.factory import set_depth_model
from octolog.tracker.slam import RgbdSlam
from octolog.tracker.depth_bias import MIN_POINTS, estimate_depth_bias


def _readings(beta: float, noise: float, n_points: int = 600, seed: int = 0):
    """Points in a room seen from 12 keyframes along a path, each reading at 1/z + beta (short if
    beta > 0) with depth noise growing with z^2: the estimator's inputs, and the map's depths."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-3, -1, 2], [3, 1, 6], (n_points, 3))
    rows = []
    for k in range(12):
        yaw = 0.05 * k
        R = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        t = np.array([0.3 * k - 1.5, 0.0, -0.2 * k])
        cam = (pts - t) @ R  # camera_from_world
        for j, p in enumerate(cam):
            if p[2] > 0.5:
                z_read = 1.0 / (1.0 / p[2] + beta) + noise * p[2] ** 2 * rng.standard_normal()
                rows.append((k, j, p / p[2] * z_read, p[2], R, t))
    k, j, xyz, z_map, R, t = zip(*rows)
    rotations = np.array([r for _, r in sorted({a: b for a, b in zip(k, R)}.items())])
    translations = np.array([v for _, v in sorted({a: b for a, b in zip(k, t)}.items())])
    return rotations, translations, np.array(k), np.array(j), np.array(xyz), np.array(z_map)


@pytest.mark.parametrize("beta", [0.0023, -0.002, 0.0])
def test_the_offset_is_recovered_from_readings_of_known_bias(beta):
    est = estimate_depth_bias(*_readings(beta, noise=1.4e-3))
    assert est is not None and est.sigma < 2e-4
    assert abs(est.inverse_offset - beta) < 3e-4, est
    assert est.confident == (beta != 0.0)
    assert abs(est.scale - 1) < 0.003
    # the bias by range: a reading at z is off by about -beta z^2 (short when beta > 0)
    assert est.bias_m[4.0] == pytest.approx(4.0 / (1 + est.inverse_offset * 4.0) - 4.0)
    # measured band by band on its own: the same offset in each
    assert est.bands
    for z, (offset, sigma, readings) in est.bands.items():
        assert abs(offset - beta) < 3 * sigma + 1e-4, (z, offset, sigma, readings)


def test_noise_alone_is_no_bias():
    """Depth noise is in the readings, not in the fit's regressor (the map's depth): pure noise,
    three times the Kinect's, gives an offset near zero rather than the errors-in-variables pull."""
    est = estimate_depth_bias(*_readings(0.0, noise=4.3e-3, seed=1))
    assert abs(est.inverse_offset) < 3 * est.sigma + 1e-4, est


def test_too_few_points_give_no_estimate():
    r = _readings(0.001, noise=1e-3, n_points=MIN_POINTS // 4)
    assert estimate_depth_bias(*r) is None


def test_the_correction_setting_is_checked():
    cfg = TrackerConfig()
    bad = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, inverse_offset=0.1))
    with pytest.raises(ConfigError, match="depth.inverse_offset"):
        bad.validate()


def test_a_cameras_depth_model_makes_far_readings_bearings_and_leaves_the_known_cameras_as_they_are():
    """kit/depthmodel.py through the tracker: the TUM Kinect's and the D455's models change no
    parameter (their metric ranges, 14 and 9 m, lie beyond tracker.depth.max_m); a 50 mm stereo
    camera at 280 px (metric to 3.5 m) makes the tracker take no reading beyond that range."""
    params = TrackerConfig().odometry_params()
    for model in (depthmodel.KINECT, depthmodel.d455(382.0)):
        assert with_depth_model(params, model) == params
    weak = depthmodel.realsense("Intel RealSense D435", 280.0)
    assert 3.0 < weak.metric_range_m < 4.0
    frame = SyntheticScene(n_frames=2).render(0)
    far = []
    for model in (None, weak):
        odo = RgbdSlam(params)
        set_depth_model(odo, model)
        odo.track(frame)
        far.append(float(odo.map.keyframes[0].feats.z.max()))
    assert far[0] > weak.metric_range_m >= far[1] > 0, far


def test_the_bias_is_reported_in_disparity_pixels_when_the_camera_is_known():
    est = estimate_depth_bias(*_readings(0.0023, noise=1.4e-3))
    assert est.disparity_px is None
    known = est.after(0.001, 1, depthmodel.KINECT.fb)
    assert known.disparity_px == pytest.approx((est.inverse_offset + 0.001) * 43.5)
    assert f"{known.disparity_px:+.3f} px" in known.summary() and known.as_dict()["disparity_offset_px"] == known.disparity_px
