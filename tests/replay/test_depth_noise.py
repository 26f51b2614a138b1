"""The synthetic depth sensors (replay/depth_noise.py) and the tracker's scale under them.

The noise models are checked against their own specification (sigma_z growing with z^2, disparity
steps, invalid bands at discontinuities); the tracker is then run on the synthetic room with each
model, along a slow and a fast path, and its Sim(3) scale must stay within 0.2 % of 1.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from octolog.replay import depth_noise
from octolog.replay.synthetic import SyntheticScene

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import depth_scale  # noqa: E402  (bench/depth_scale.py: the same runs as the table)


@pytest.fixture
def track_scene():
    """bench/depth_scale.py's track_scene: the same runs as its table (each noisy frame rendered
    once for all of them: replay/synthetic.py's frame cache)."""
    return depth_scale.track_scene


@pytest.mark.parametrize("name", ["kinect", "d455"])
@pytest.mark.parametrize("z", [1.0, 2.5, 4.0])
def test_depth_error_grows_with_the_square_of_distance_and_is_unbiased(name, z):
    """On a flat wall at z: the spread is sigma_d z^2 / (f b) plus the disparity step's rounding,
    within 15 %; the mean stays within a tenth of that spread of the truth (no bias of its own)."""
    s = depth_noise.SENSORS[name]
    exact = np.full((300, 300), z)
    out = depth_noise.apply(exact, np.full((300, 300, 3), 128, np.uint8), s, np.random.default_rng(1))
    got = out[out > 0]
    fb = s.focal_px * s.baseline_m
    d = fb / z
    step_z = z * s.step_px / d  # one disparity step in depth
    sigma = np.hypot(z * s.sigma_px / d, step_z / np.sqrt(12))
    assert got.size > 0.98 * out.size  # a flat wall: only the random dropouts
    assert abs(got.std() / sigma - 1) < 0.15, (got.std(), sigma)
    assert abs(got.mean() - z) < 0.1 * sigma + 1e-4
    levels = np.unique(np.round(fb / got / s.step_px, 6))
    assert np.allclose(levels, np.round(levels))  # every reading is a whole number of disparity steps


@pytest.mark.parametrize("name", ["kinect", "d455"])
def test_a_disparity_offset_biases_depth_with_the_square_of_distance(name):
    """`bias_px` (the synthetic source's `bias=PX`): the mean reading on a flat wall is short by
    z^2 bias / (f b) within 15 % (0.1 px: 0.9-1.1 % at 4 m), at every distance; negative reads long."""
    s = depth_noise.SENSORS[name]
    grey = np.full((300, 300, 3), 128, np.uint8)
    for z in (1.0, 2.5, 4.0):
        for bias in (0.1, -0.1):
            exact = np.full((300, 300), z)
            out = depth_noise.apply(exact, grey, s, np.random.default_rng(2), bias_px=bias)
            unbiased = depth_noise.apply(exact, grey, s, np.random.default_rng(2))
            ok = (out > 0) & (unbiased > 0)
            shift = float(np.mean(unbiased[ok]) - np.mean(out[ok]))
            want = z * z * bias / (s.focal_px * s.baseline_m)
            assert abs(shift - want) < 0.15 * abs(want), (z, bias, shift, want)


def test_a_depth_discontinuity_reads_zero_along_its_edge():
    s = depth_noise.SENSORS["d455"]
    exact = np.full((50, 50), 3.0)
    exact[:, 25:] = 1.0  # a box in front of a wall
    out = depth_noise.apply(exact, np.full((50, 50, 3), 128, np.uint8), s, np.random.default_rng(2))
    assert (out[:, 24:26] == 0).all()
    assert (out[:, :20] > 0).mean() > 0.98 and (out[:, 30:] > 0).mean() > 0.98


def test_dark_surfaces_lose_depth_under_structured_light_only():
    exact, dark = np.full((100, 100), 2.0), np.full((100, 100, 3), 5, np.uint8)
    rng = np.random.default_rng(3)
    assert (depth_noise.apply(exact, dark, depth_noise.SENSORS["kinect"], rng) == 0).mean() > 0.5
    assert (depth_noise.apply(exact, dark, depth_noise.SENSORS["d455"], rng) == 0).mean() < 0.01


def test_noisy_frames_are_deterministic_and_differ_from_exact_ones():
    """The renderer itself (`render_frame`, not the frame cache in front of it)."""
    a_rgb, a_depth = SyntheticScene(n_frames=3, width=160, height=120, depth_noise="d455").render_frame(2)
    _, b_depth = SyntheticScene(n_frames=3, width=160, height=120, depth_noise="d455").render_frame(2)
    exact_rgb, exact_depth = SyntheticScene(n_frames=3, width=160, height=120).render_frame(2)
    assert np.array_equal(a_depth, b_depth) and np.array_equal(a_rgb, exact_rgb)
    both = (a_depth > 0) & (exact_depth > 0)
    assert 0 < np.mean(a_depth[both] != exact_depth[both])
    with pytest.raises(ValueError, match="depth_noise"):
        SyntheticScene(depth_noise="lidar")


def test_sensor_models_share_the_rendered_view_and_read_it_as_a_fresh_render_would(monkeypatch, tmp_path):
    """Scenes that differ only in the depth sensor, its offset, the blur or the blank stretch render
    the room once (the exact view beside the frame cache); each frame's depth is still the one its
    own sensor reads from an uncached render."""
    monkeypatch.setenv("OCTOLOG_CACHE", str(tmp_path))
    size = {"n_frames": 3, "width": 160, "height": 120}
    SyntheticScene(**size, depth_noise="kinect").render(1)
    other = SyntheticScene(**size, depth_noise="d455", depth_bias_px=0.1, exposure_ms=5.0, blank_s=0.01)
    fresh = other.render_pose(other.pose(1), np.random.default_rng([0, 1]), 1 / 30)
    monkeypatch.setattr(SyntheticScene, "view", lambda *_a, **_k: pytest.fail("the view was rendered again"))
    frame = other.render(1)
    assert np.array_equal(frame.depth, fresh[1]) and not np.array_equal(frame.rgb, fresh[0])  # blurred


@pytest.mark.slow
@pytest.mark.parametrize(("noise", "every"), [("kinect", 1), ("kinect", 3), ("d455", 1), ("d455", 3)],
                         ids=["kinect-slow", "kinect-fast", "d455-slow", "d455-fast"])
def test_the_tracker_has_no_scale_bias_under_sensor_noise(noise, every, track_scene):
    """Sim(3) scale within 0.2 % of 1 on the synthetic room (exact truth), slow and fast path, with
    tracker.depth.correct_bias on: an unbiased camera's map gives no confident bias, so nothing is
    corrected (and the outputs are the default's)."""
    r = track_scene(noise, 240, every, online=True)
    assert r["tracked"] == r["frames"]
    assert r["corrections"] == 0 and r["offset"] == 0.0, r
    assert abs(r["scale"] - 1) < 0.002, r
    # and the map finds no depth bias: less than a third of a 0.1 px disparity offset's
    s = depth_noise.SENSORS[noise]
    assert abs(r["depth_bias"].inverse_offset) < 0.1 / (s.focal_px * s.baseline_m) / 3, r["depth_bias"]


@pytest.mark.slow
@pytest.mark.parametrize(("noise", "every", "bias_px"), [("kinect", 1, 0.1), ("d455", 3, -0.1)],
                         ids=["kinect-slow-short", "d455-fast-long"])
def test_the_map_measures_a_biased_camera_and_its_correction_restores_the_scale(noise, every, bias_px, track_scene):
    """A disparity offset of 0.1 px (depth off by about 0.9-1.1 % at 4 m): the trajectory's scale
    comes out more than 0.3 % off; the map's estimate (tracker/depth_bias.py) gives the bias at 1-5 m
    within a third of the truth; tracking again with tracker.depth.correct_bias, the correction
    found while tracking is within a third of the truth, the Sim(3) scale within 0.3 % of 1 and the
    SE(3) ATE lower."""
    s = depth_noise.SENSORS[noise]
    beta = bias_px / (s.focal_px * s.baseline_m)
    biased = track_scene(noise, 240, every, bias_px=bias_px)
    assert abs(biased["scale"] - 1) > 0.003, biased
    est = biased["depth_bias"]
    assert est.confident
    for z, got in est.bias_m.items():
        want = z / (1.0 + beta * z) - z  # what the camera reads at true range z, minus z
        assert abs(got - want) < abs(want) / 3, (z, got, want)
    # and measured band by band, where the room has readings (2-4 m)
    assert len(est.band_bias_m) >= 2, est.bands
    for z, (got, _) in est.band_bias_m.items():
        want = z / (1.0 + beta * z) - z
        assert abs(got - want) < abs(want) / 3, (z, got, want)
    online = track_scene(noise, 240, every, bias_px=bias_px, online=True)
    assert online["corrections"] >= 1 and abs(online["offset"] - beta) < abs(beta) / 3, online
    assert abs(online["scale"] - 1) < 0.003, online
    assert online["ate_m"] < biased["ate_m"], (online, biased)
