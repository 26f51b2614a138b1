"""Tests of the RGB-D odometry core (tracker.odometry, tracker.features).

Synthetic frames are ray-cast here from three textured planes seen by a camera on a known path,
so the recovered motion can be checked exactly; the real-data test needs OCTOLOG_DATA.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import tum_first300

from octolog.kit.errors import ConfigError, TrackingError
from octolog.kit.geometry import Intrinsics, RgbdFrame, invert
from octolog.tracker.config import DepthParams, TrackerConfig
from octolog.tracker.features import OrbExtractor, Undistorter, bucket_select, hamming, match_by_projection
from octolog.tracker.interface import Tracker, TrackingState, TrackResult
from octolog.tracker.slam import RgbdSlam
from octolog.tracker.pose import rotation_angle

W, H = 640, 480
INTR = Intrinsics(W, H, 525.0, 525.0, 319.5, 239.5, ())
DEPTH_SCALE = 1.0 / 5000.0
FRAME_DT_NS = 33_333_333


# ----------------------------------------------------------------------------------------------
# Synthetic scene: a back wall, a floor and a slanted panel with random texture, ray-cast.


def _texture(seed: int, size: int = 1024) -> np.ndarray:
    """Random blocks and blobs: many corners at several scales, like a cluttered poster."""
    rng = np.random.default_rng(seed)
    tex = cv2.resize(rng.integers(0, 256, (size // 16, size // 16), dtype=np.uint8), (size, size),
                     interpolation=cv2.INTER_NEAREST)
    for _ in range(400):
        x, y = rng.integers(0, size, 2)
        w, h = rng.integers(8, 60, 2)
        cv2.rectangle(tex, (int(x), int(y)), (int(x + w), int(y + h)), int(rng.integers(0, 256)), -1)
    for _ in range(200):
        x, y = rng.integers(0, size, 2)
        cv2.circle(tex, (int(x), int(y)), int(rng.integers(4, 25)), int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(tex, (3, 3), 0.8)


# (origin, axis u, axis v) of each plane in world coordinates; texture spans 2 m x 2 m per tile.
PLANES = [
    (np.array([-2.0, -1.5, 3.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])),  # wall z=3
    (np.array([-2.0, 0.8, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])),  # floor y=0.8
    (np.array([0.3, -1.0, 1.6]), np.array([0.6, 0.0, 0.8]), np.array([0.0, 1.0, 0.0])),  # slanted panel
]
PANEL_EXTENT = (1.2, 1.4)  # the panel is finite so it occludes part of the wall
TEXEL_M = 2.0 / 1024


def render(world_from_camera: np.ndarray, textures: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Colour (H, W, 3) uint8 and depth (H, W) uint16 of the scene from a camera pose."""
    Kinv = np.linalg.inv(INTR.matrix)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays_c = np.stack([u, v, np.ones_like(u)], axis=-1) @ Kinv.T  # z component = 1
    R, o = world_from_camera[:3, :3], world_from_camera[:3, 3]
    rays_w = rays_c @ R.T
    best_t = np.full((H, W), np.inf)
    gray = np.zeros((H, W), np.float32)
    for i, (p0, a, b) in enumerate(PLANES):
        n = np.cross(a, b)
        denom = rays_w @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p0 - o) @ n) / denom
        hit = o + rays_w * t[..., None]
        s = (hit - p0) @ a
        r = (hit - p0) @ b
        ok = np.isfinite(t) & (t > 0.05) & (t < best_t)
        if i == 2:
            ok &= (s >= 0) & (s <= PANEL_EXTENT[0]) & (r >= 0) & (r <= PANEL_EXTENT[1])
        tex = textures[i]
        mx = np.mod(s / TEXEL_M, tex.shape[1] - 1).astype(np.float32)
        my = np.mod(r / TEXEL_M, tex.shape[0] - 1).astype(np.float32)
        val = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
        gray = np.where(ok, val.astype(np.float32), gray)
        best_t = np.where(ok, t, best_t)
    depth = np.where(np.isfinite(best_t), best_t, 0.0)  # rays have z = 1, so t is the depth
    depth_units = np.clip(np.rint(depth / DEPTH_SCALE), 0, 65535).astype(np.uint16)
    g8 = np.clip(np.rint(gray), 0, 255).astype(np.uint8)
    return np.repeat(g8[..., None], 3, axis=2), depth_units


def true_poses(n: int) -> list[np.ndarray]:
    """A smooth path: 1.2 cm and ~0.4 degrees per frame, mixing all axes."""
    poses = []
    for k in range(n):
        t = np.array([0.012 * k, -0.004 * k, 0.006 * k])
        angles = np.radians([0.3 * k, -0.4 * k, 0.15 * k])
        q = cv2.Rodrigues(angles)[0]
        T = np.eye(4)
        T[:3, :3] = q
        T[:3, 3] = t
        poses.append(T)
    return poses


@pytest.fixture(scope="module")
def scene() -> tuple[list[RgbdFrame], list[np.ndarray]]:
    textures = [_texture(s) for s in (1, 2, 3)]
    poses = true_poses(12)
    frames = []
    for k, T in enumerate(poses):
        rgb, depth = render(T, textures)
        frames.append(RgbdFrame(k, 1_000_000_000 + k * FRAME_DT_NS, rgb, depth, DEPTH_SCALE, INTR))
    return frames, poses


def _track_all(frames: list[RgbdFrame]) -> list[TrackResult]:
    odo = RgbdSlam()
    return [odo.track(f) for f in frames]


# ----------------------------------------------------------------------------------------------
# Synthetic motion.


def test_synthetic_motion_is_recovered(scene) -> None:
    frames, poses = scene
    results = _track_all(frames)
    assert results[0].state == TrackingState.INIT and results[0].is_keyframe and results[0].keyframe_id == 0
    np.testing.assert_array_equal(results[0].world_from_camera, np.eye(4))
    assert [r.state for r in results[1:]] == [TrackingState.OK] * (len(frames) - 1)
    for r, T in zip(results, poses):
        # World = first camera, and the true first pose is the identity, so they compare directly.
        err = invert(T) @ r.world_from_camera
        assert r.world_from_camera.dtype == np.float64 and r.world_from_camera.shape == (4, 4)
        assert np.linalg.norm(err[:3, 3]) < 0.005, f"frame {r.seq}: translation error {err[:3, 3]}"
        assert np.degrees(rotation_angle(err[:3, :3])) < 0.3, f"frame {r.seq}: rotation error"
        assert r.n_inliers >= 100 and r.n_matches >= r.n_inliers or r.state == TrackingState.INIT
    # 13 cm of motion with the default thresholds must have produced new keyframes, numbered 1, 2...
    kf_ids = [r.keyframe_id for r in results if r.is_keyframe]
    assert kf_ids == list(range(len(kf_ids))) and len(kf_ids) >= 2
    assert all(r.keyframe_id == -1 for r in results if not r.is_keyframe)


def test_skipped_frames_are_bridged(scene) -> None:
    """Every other frame: twice the motion per step, the constant-velocity prior must keep up."""
    frames, poses = scene
    results = _track_all(frames[::2])
    assert all(r.state in (TrackingState.INIT, TrackingState.OK) for r in results)
    err = invert(poses[-2]) @ results[-1].world_from_camera
    assert np.linalg.norm(err[:3, 3]) < 0.005


# ----------------------------------------------------------------------------------------------
# Determinism.


def _digest(results: list[TrackResult]) -> str:
    h = hashlib.sha256()
    for r in results:
        h.update(r.world_from_camera.tobytes())
        h.update(f"{r.seq} {r.stamp_ns} {r.state} {r.keyframe_id} {r.n_matches} {r.n_inliers}".encode())
    return h.hexdigest()


def test_deterministic_in_process(scene) -> None:
    frames, _ = scene
    assert _digest(_track_all(frames)) == _digest(_track_all(frames))


def test_deterministic_across_processes(scene) -> None:
    """A fresh interpreter (other hash seed, fresh OpenCV state) gives byte-identical poses."""
    frames, _ = scene
    here = _digest(_track_all(frames))
    code = (
        "import importlib.util, sys\n"
        f"sys.path.insert(0, {str(Path(__file__).resolve().parents[1])!r})\n"
        f"spec = importlib.util.spec_from_file_location('t', {str(Path(__file__))!r})\n"
        "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)\n"
        "tex = [m._texture(s) for s in (1, 2, 3)]\n"
        "fr = []\n"
        "for k, T in enumerate(m.true_poses(12)):\n"
        "    rgb, d = m.render(T, tex)\n"
        "    fr.append(m.RgbdFrame(k, 1_000_000_000 + k * m.FRAME_DT_NS, rgb, d, m.DEPTH_SCALE, m.INTR))\n"
        "print(m._digest(m._track_all(fr)))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONHASHSEED": "12345"}, cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == here


# ----------------------------------------------------------------------------------------------
# Failure handling.


def test_black_frame_is_lost_and_tracking_resumes(scene) -> None:
    frames, poses = scene
    odo = RgbdSlam()
    out = [odo.track(f) for f in frames[:4]]
    black = RgbdFrame(4, frames[4].stamp_ns, np.zeros_like(frames[4].rgb), frames[4].depth, DEPTH_SCALE, INTR)
    lost = odo.track(black)
    assert lost.state == TrackingState.LOST and not lost.is_keyframe and lost.keyframe_id == -1
    # The LOST pose is the constant-velocity prediction: close to the truth on this smooth path.
    err = invert(poses[4]) @ lost.world_from_camera
    assert np.linalg.norm(err[:3, 3]) < 0.01
    # Without depth the frame still tracks by 2D-3D matches to the map, but cannot be a keyframe.
    no_depth = RgbdFrame(5, frames[5].stamp_ns, frames[5].rgb, np.zeros_like(frames[5].depth), DEPTH_SCALE, INTR)
    r5 = odo.track(no_depth)
    assert r5.state == TrackingState.OK and not r5.is_keyframe
    assert np.linalg.norm((invert(poses[5]) @ r5.world_from_camera)[:3, 3]) < 0.005
    back = [odo.track(f) for f in frames[6:]]
    assert [r.state for r in back] == [TrackingState.OK] * len(back)
    err = invert(poses[-1]) @ back[-1].world_from_camera
    assert np.linalg.norm(err[:3, 3]) < 0.005
    assert out[0].state == TrackingState.INIT


def test_recovers_after_a_long_gap(scene) -> None:
    """Several unusable frames make the prediction drift; tracking must resume from the map."""
    frames, poses = scene
    odo = RgbdSlam()
    for f in frames[:3]:
        odo.track(f)
    for k in range(3, 9):
        blank = RgbdFrame(k, frames[k].stamp_ns, np.zeros_like(frames[k].rgb), np.zeros_like(frames[k].depth),
                          DEPTH_SCALE, INTR)
        assert odo.track(blank).state == TrackingState.LOST
    r = odo.track(frames[9])
    assert r.state == TrackingState.OK
    assert np.linalg.norm((invert(poses[9]) @ r.world_from_camera)[:3, 3]) < 0.005


def test_a_jump_the_motion_cannot_explain_on_weak_support_is_lost_not_published(scene) -> None:
    """The camera's view jumps five frames ahead between two frames 33 ms apart: a pose that leaves
    the constant-velocity prediction by more than tracking.max_jump_m. Called weak (any inlier count
    below jump_support), it is LOST, not published; the next frame is taken without the gate (the
    prediction after LOST is a guess) and lands where the camera truly is. With the default support
    threshold the same frame, matched by hundreds of inliers, is tracked."""
    import dataclasses

    from octolog.tracker.config import TrackingParams

    frames, poses = scene
    jump = RgbdFrame(6, frames[6].stamp_ns, frames[11].rgb, frames[11].depth, DEPTH_SCALE, INTR)
    after = RgbdFrame(7, frames[7].stamp_ns, frames[11].rgb, frames[11].depth, DEPTH_SCALE, INTR)
    strict = TrackerConfig(tracking=dataclasses.replace(TrackingParams(), max_jump_m=0.03, jump_support=10**6))
    odo = RgbdSlam(strict.odometry_params())
    assert [odo.track(f).state for f in frames[:6]] == [TrackingState.INIT] + [TrackingState.OK] * 5
    r = odo.track(jump)
    assert r.state == TrackingState.LOST and odo.rejected_jumps == 1 and not r.is_keyframe
    back = odo.track(after)
    assert back.state == TrackingState.OK
    assert np.linalg.norm((invert(poses[11]) @ back.world_from_camera)[:3, 3]) < 0.005
    # the same jump with the default support threshold: strong evidence, tracked
    odo = RgbdSlam()
    for f in frames[:6]:
        odo.track(f)
    r = odo.track(jump)
    assert r.n_inliers >= TrackingParams().jump_support and r.state == TrackingState.OK and odo.rejected_jumps == 0
    assert np.linalg.norm((invert(poses[11]) @ r.world_from_camera)[:3, 3]) < 0.005


def test_frames_before_initialisation_are_lost() -> None:
    odo = RgbdSlam()
    assert isinstance(odo, Tracker)
    blank = RgbdFrame(0, 0, np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.uint16), DEPTH_SCALE, INTR)
    r = odo.track(blank)
    assert r.state == TrackingState.LOST and r.keyframe_id == -1
    np.testing.assert_array_equal(r.world_from_camera, np.eye(4))


def test_configuration_mistakes_raise() -> None:
    odo = RgbdSlam()
    small = RgbdFrame(0, 0, np.zeros((240, 320, 3), np.uint8), np.zeros((240, 320), np.uint16), DEPTH_SCALE, INTR)
    with pytest.raises(TrackingError, match="intrinsics"):
        odo.track(small)
    bad_depth = RgbdFrame(0, 0, np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32), DEPTH_SCALE, INTR)
    with pytest.raises(TrackingError, match="depth"):
        odo.track(bad_depth)
    # parameters are checked once, where they are built from the config
    with pytest.raises(ConfigError, match="tracker.n_features 10"):
        RgbdSlam(TrackerConfig(n_features=10).odometry_params())
    with pytest.raises(ConfigError, match="tracker.depth.max_m 1.0"):
        RgbdSlam(TrackerConfig(depth=DepthParams(min_m=3.0, max_m=1.0)).odometry_params())


# ----------------------------------------------------------------------------------------------
# Feature helpers.


def test_undistortion_inverts_plumb_bob() -> None:
    intr = Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3, (0.262383, -0.953104, -0.005358, 0.002628, 1.163314))
    rng = np.random.default_rng(0)
    ideal = rng.uniform([40, 40], [600, 440], (200, 2))
    rays = np.c_[(ideal - [intr.cx, intr.cy]) / [intr.fx, intr.fy], np.ones(200)]
    raw, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), intr.matrix, np.array(intr.distortion))
    back = Undistorter(intr)(raw.reshape(-1, 2))
    assert np.abs(back - ideal).max() < 0.01
    assert np.array_equal(Undistorter(INTR)(ideal), ideal)


def test_bucketing_spreads_features() -> None:
    rng = np.random.default_rng(1)
    # 2000 strong corners crowded in one corner, 200 weak ones elsewhere.
    crowd = rng.uniform([0, 0], [80, 60], (2000, 2))
    rest = rng.uniform([80, 60], [640, 480], (200, 2))
    pts = np.vstack([crowd, rest])
    resp = np.r_[np.full(2000, 10.0), np.full(200, 1.0)]
    keep = bucket_select(pts, resp, 640, 480, 500, 8, 6)
    assert keep.size == 500 and np.unique(keep).size == 500
    assert np.sum(keep >= 2000) == 200  # every weak, spread-out corner survives
    assert np.array_equal(keep, bucket_select(pts, resp, 640, 480, 500, 8, 6))


def test_low_contrast_frames_fall_back_to_the_low_fast_threshold() -> None:
    """FAST runs at 20 first (cheap on textured frames) and at 7 where that finds too few corners."""
    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.mean()) / texture.std()
    strong = np.clip(128 + 40 * texture, 0, 255).astype(np.uint8)
    faint = np.clip(128 + 4 * texture, 0, 255).astype(np.uint8)  # a dim, low-contrast view
    high_only = OrbExtractor(n_features=500, fast_threshold=20, min_fast_threshold=20)
    with_fallback = OrbExtractor(n_features=500, fast_threshold=20, min_fast_threshold=7)
    assert len(high_only.extract(strong)[0]) == 500  # textured: the first pass is enough
    assert np.array_equal(with_fallback.extract(strong)[2], high_only.extract(strong)[2])
    n_high, n_fallback = len(high_only.extract(faint)[0]), len(with_fallback.extract(faint)[0])
    assert n_high < 250 and n_fallback == 500, (n_high, n_fallback)


def test_match_by_projection_agrees_with_brute_force() -> None:
    rng = np.random.default_rng(2)
    kp_uv = rng.uniform([0, 0], [640, 480], (400, 2))
    kp_desc = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    src = rng.integers(0, 400, 300)
    proj_uv = kp_uv[src] + rng.normal(0, 3, (300, 2))
    proj_desc = kp_desc[src].copy()
    flip = rng.integers(0, 32, (300, 3))
    for i in range(300):  # a few bit flips so distances are small but not zero
        proj_desc[i, flip[i]] ^= np.uint8(1)
    mi, ki, dd = match_by_projection(proj_uv, proj_desc, kp_uv, kp_desc, radius=12.0, max_distance=50, ratio=0.9)
    # Reference: exhaustive search with the same rules.
    d2 = ((proj_uv[:, None, :] - kp_uv[None, :, :]) ** 2).sum(-1)
    ham = np.array([[int(np.unpackbits(a ^ b).sum()) for b in kp_desc] for a in proj_desc])
    ref = {}
    for i in range(300):
        cand = np.flatnonzero(d2[i] <= 144.0)
        if cand.size == 0:
            continue
        order = cand[np.lexsort((cand, ham[i, cand]))]
        best = order[0]
        second = ham[i, order[1]] if order.size > 1 else np.inf
        if ham[i, best] <= 50 and ham[i, best] < 0.9 * second:
            ref[i] = (int(best), int(ham[i, best]))
    by_kp: dict[int, tuple[int, int]] = {}
    for i, (k, d) in sorted(ref.items()):
        if k not in by_kp or d < by_kp[k][1]:
            by_kp[k] = (i, d)
    expected = sorted((i, k, d) for k, (i, d) in by_kp.items())
    assert list(zip(mi.tolist(), ki.tolist(), dd.tolist())) == expected
    assert len(expected) > 200
    assert np.array_equal(dd, hamming(proj_desc[mi], kp_desc[ki]))


# ----------------------------------------------------------------------------------------------
# Real data.


def _ate_rmse(gt_path: Path, stamps_ns: list[int], poses: list[np.ndarray]) -> float:
    """ATE RMSE after SE(3) Umeyama alignment, nearest ground truth within 20 ms."""
    gt = np.loadtxt(gt_path, comments="#")
    gt_t = gt[:, 0]
    est, ref = [], []
    for s, T in zip(stamps_ns, poses):
        t = s * 1e-9
        j = int(np.argmin(np.abs(gt_t - t)))
        if abs(gt_t[j] - t) < 0.02:
            est.append(T[:3, 3])
            ref.append(gt[j, 1:4])
    P, Q = np.array(est), np.array(ref)
    mp, mq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    aligned = (P - mp) @ R.T + mq
    return float(np.sqrt(((aligned - Q) ** 2).sum(1).mean()))


def _online_poses(session: Path) -> tuple[list[int], list[np.ndarray], list[int]]:
    """A session's online poses: each tracked frame's pose as the tracker published it
    (tracker/pose), before loop closing or the final BA moved it; and every frame's tracking state
    (tracker/status, the wire codes)."""
    from octolog.kit.mcaplog import read_wire
    from octolog.schemas import codec, posemsgs
    from octolog.schemas.topics import POSE, TRACKING_STATUS

    log = session / "session.mcap"
    msgs = [codec.decode(m.data, POSE.msgtype) for m in read_wire(log, [POSE.name])]
    states = [codec.decode(m.data, TRACKING_STATUS.msgtype).state for m in read_wire(log, [TRACKING_STATUS.name])]
    return [codec.stamp_ns(m.header) for m in msgs], [posemsgs.pose_matrix(m.pose) for m in msgs], states


@pytest.mark.slow
def test_tum_fr1_xyz_first300_accuracy(first300_run) -> None:
    """Online ATE on TUM fr1/xyz first300 with the rolling-shutter model, as `octolog run` sets it
    from the source (config.for_source): the poses the tracker published in the shared whole-pipeline
    run (`first300_run`'s session log); without the model: the same frames tracked here."""
    import tomllib

    from octolog.replay.sources import open_source
    from octolog.schemas import codec
    from octolog.schemas.topics import TRACKING_STATUS

    src = open_source(f"tum:{tum_first300()}")
    seq = src.seq
    assert seq.groundtruth is not None
    assert src.readout_s > 0.0  # freiburg1's Kinect has a rolling shutter
    out = first300_run[0]
    tracker = tomllib.loads((out / "config.toml").read_text())["tracker"]
    assert tracker["rolling_shutter_ms"] == pytest.approx(1e3 * src.readout_s)
    stamps, poses, states = _online_poses(out)
    codes = codec.msgtype(TRACKING_STATUS.msgtype)
    assert states[0] == codes.INIT and states[1:] == [codes.OK] * (len(states) - 1)

    odo = RgbdSlam(TrackerConfig(rolling_shutter_ms=0.0).odometry_params())
    results = [odo.track(f) for f in seq.frames()]
    assert results[0].state == TrackingState.INIT
    assert [r.state for r in results[1:]] == [TrackingState.OK] * (len(results) - 1)
    assert [r.stamp_ns for r in results] == stamps and len(states) == len(results)  # the same frames

    # Online poses (no final global BA). Measured 0.78 cm with the rolling-shutter model and
    # 1.16 cm without; ORB-SLAM3 reaches ~1.15 cm here. The target is <= 1 cm; the model
    # must earn its keep by a clear margin, not by noise.
    with_model = _ate_rmse(seq.groundtruth, stamps, poses)
    without = _ate_rmse(seq.groundtruth, [r.stamp_ns for r in results], [r.world_from_camera for r in results])
    print(f"online ATE RMSE: {with_model * 100:.2f} cm with the rolling-shutter model, {without * 100:.2f} cm without")
    assert with_model <= 0.010, f"ATE RMSE {with_model * 100:.2f} cm with the rolling-shutter model"
    assert with_model < 0.85 * without, (with_model, without)
