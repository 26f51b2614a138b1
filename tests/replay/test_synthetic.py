"""Tests of the synthetic textured room (replay.synthetic)."""

from __future__ import annotations

import hashlib
import math
import os
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from octolog.kit.geometry import pose_to_matrix
from octolog.replay.synthetic import EPOCH_NS, SyntheticScene
from octolog.replay.synthetic_room import OBJECTS, ROOM

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def small() -> SyntheticScene:
    """160x120 (same field of view as 640x480), one full 18 s loop."""
    return SyntheticScene(n_frames=540, width=160, height=120)


def _ray_hit(origin: np.ndarray, d: np.ndarray) -> float:
    """Analytic ray parameter of the first hit: room exit or nearest object entry (slab method)."""

    def slabs(box, o, dd):
        R = box.axes()
        lo_ = (o - box.centre()) @ R.T
        dl = dd @ R.T
        with np.errstate(divide="ignore"):
            t1 = (-box.half() - lo_) / dl
            t2 = (box.half() - lo_) / dl
        return np.minimum(t1, t2).max(), np.maximum(t1, t2).min()

    best = slabs(ROOM, origin, d)[1]
    for box in OBJECTS:
        t_in, t_out = slabs(box, origin, d)
        if t_in <= t_out and 0 < t_in < best:
            best = t_in
    return best


def test_intrinsics_defaults() -> None:
    K = SyntheticScene().intrinsics
    assert (K.width, K.height, K.fx, K.fy, K.cx, K.cy, K.distortion) == (640, 480, 525.0, 525.0, 319.5, 239.5, ())


def test_frame_format(small: SyntheticScene) -> None:
    f = small.render(7)
    assert f.seq == 7 and f.stamp_ns == small.stamp_ns(7)
    assert f.rgb.shape == (120, 160, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (120, 160) and f.depth.dtype == np.uint16
    assert f.depth_scale_m == 0.001 and f.intrinsics == small.intrinsics


def test_depth_facing_wall_is_constant() -> None:
    """Looking straight at the -x wall from 2 m, every pixel of that wall reads 2000 mm."""
    scene = SyntheticScene(n_frames=1, width=160, height=120)
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # x: +y, y: -z, z: -x
    T[:3, 3] = (-1.0, 0.3, 1.4)
    rgb, depth = scene.render_pose(T)
    assert depth[40:80, 60:100].min() == 2000 and depth[40:80, 60:100].max() == 2000
    assert rgb.std() > 20


def test_depth_matches_analytic_ray_casting(small: SyntheticScene) -> None:
    K = small.intrinsics
    rng = np.random.default_rng(1)
    for i in (0, 130, 260, 400):
        T = small.pose(i)
        depth = small.render(i).depth
        for u, v in rng.integers(0, (K.width, K.height), size=(25, 2)):
            d_cam = np.array([(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0])
            z = _ray_hit(T[:3, 3], T[:3, :3] @ d_cam)  # unit z in camera: ray parameter = depth
            got = depth[v, u] * 0.001
            # Pixels straddling an edge may hit either side; skip those.
            near = [
                _ray_hit(T[:3, 3], T[:3, :3] @ (d_cam + np.array([du, dv, 0.0]) * 1e-3))
                for du, dv in ((1, 0), (-1, 0), (0, 1), (0, -1))
            ]
            if max(abs(np.array(near) - z)) > 0.02:
                continue
            assert abs(got - z) <= 0.0006, (i, u, v, got, z)


def test_backprojected_depth_lies_on_mesh(small: SyntheticScene) -> None:
    K = small.intrinsics
    for i in (5, 200, 333):
        f = small.render(i)
        z = f.depth_m().astype(np.float64)
        v, u = np.nonzero(z > 0)
        assert len(u) > 0.95 * z.size
        p_cam = np.stack([(u - K.cx) / K.fx * z[v, u], (v - K.cy) / K.fy * z[v, u], z[v, u]], axis=1)
        T = small.pose(i)
        p_world = p_cam @ T[:3, :3].T + T[:3, 3]
        assert small.distance_to_surface(p_world).max() < 0.01


def test_mesh_and_surface_samples(small: SyntheticScene) -> None:
    pts = small.surface_samples(0.05)
    assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 30_000
    assert small.distance_to_surface(pts).max() < 1e-4
    assert np.all(np.abs(pts - ROOM.centre()) <= ROOM.half() + 1e-9)
    for box in OBJECTS:  # nothing hidden inside or under an object except its own faces
        inside = box.contains(pts, tol=-1e-3)
        assert not inside.any()
    # Denser spacing, more points: about area / spacing^2.
    assert len(small.surface_samples(0.025)) > 3.5 * len(pts)
    mesh = small.mesh
    assert len(mesh.triangles) == len(mesh.vertices) // 2 > 12
    area = mesh.get_surface_area()
    assert area == pytest.approx(len(pts) * 0.05**2, rel=0.1)


def test_scene_is_viewed_at_a_sensible_distance(small: SyntheticScene) -> None:
    for i in range(0, len(small), 27):
        z = small.render(i).depth_m()
        valid = z[z > 0]
        assert valid.size > 0.95 * z.size
        assert 0.5 < np.median(valid) < 4.0
        assert (valid < 0.5).mean() < 0.05


def test_colour_has_trackable_texture() -> None:
    cv2 = pytest.importorskip("cv2")
    scene = SyntheticScene(n_frames=100)
    f = scene.render(60)
    gray = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
    assert gray.std() > 25
    kps = cv2.ORB_create(nfeatures=5000).detect(gray, None)
    assert len(kps) > 1000
    # Spread over the image: every cell of a 4x4 grid has features.
    cells = {(int(k.pt[0] * 4 / 640), int(k.pt[1] * 4 / 480)) for k in kps}
    assert len(cells) == 16


def test_features_track_to_the_ground_truth_motion() -> None:
    """ORB matches between frames 3 apart, lifted with depth, give the true relative pose by PnP."""
    cv2 = pytest.importorskip("cv2")
    scene = SyntheticScene(n_frames=200)
    K = scene.intrinsics
    a, b = scene.render(120), scene.render(123)
    orb = cv2.ORB_create(nfeatures=1500)
    ka, da = orb.detectAndCompute(cv2.cvtColor(a.rgb, cv2.COLOR_RGB2GRAY), None)
    kb, db = orb.detectAndCompute(cv2.cvtColor(b.rgb, cv2.COLOR_RGB2GRAY), None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    pa = np.array([ka[m.queryIdx].pt for m in matches])
    pb = np.array([kb[m.trainIdx].pt for m in matches])
    z = a.depth_m()[np.rint(pa[:, 1]).astype(int), np.rint(pa[:, 0]).astype(int)].astype(np.float64)
    ok = z > 0
    pts = np.stack([(pa[:, 0] - K.cx) / K.fx * z, (pa[:, 1] - K.cy) / K.fy * z, z], axis=1)[ok]
    found, rvec, tvec, inliers = cv2.solvePnPRansac(pts, pb[ok], K.matrix, None, reprojectionError=2.0)
    assert found and len(inliers) > 0.6 * len(matches) > 400
    b_from_a = np.eye(4)
    b_from_a[:3, :3] = cv2.Rodrigues(rvec)[0]
    b_from_a[:3, 3] = tvec.ravel()
    truth = np.linalg.inv(scene.pose(123)) @ scene.pose(120)
    err = np.linalg.inv(truth) @ b_from_a
    assert np.linalg.norm(err[:3, 3]) < 0.02
    assert Rotation.from_matrix(err[:3, :3]).magnitude() < math.radians(0.5)


def test_render_is_deterministic(small: SyntheticScene) -> None:
    """The renderer itself (`render_frame`, not the frame cache in front of it)."""
    a = small.render_frame(42)
    b = small.render_frame(42)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    other = SyntheticScene(n_frames=540, width=160, height=120).render_frame(42)
    assert np.array_equal(a[0], other[0]) and np.array_equal(a[1], other[1])
    reseeded = SyntheticScene(n_frames=50, width=160, height=120, seed=3, texel_m=0.02)
    assert not np.array_equal(a[0], reseeded.render_frame(42)[0])


def _digest(f) -> str:
    return hashlib.sha256(f.rgb.tobytes() + f.depth.tobytes()).hexdigest()


def test_render_is_deterministic_across_processes(small: SyntheticScene) -> None:
    code = (
        "import hashlib, sys\n"
        "from octolog.replay.synthetic import SyntheticScene\n"
        "assert 'open3d' not in sys.modules  # lazy: nothing heavy at import\n"
        "rgb, depth = SyntheticScene(n_frames=540, width=160, height=120, nthreads=1).render_frame(77)\n"
        "print(hashlib.sha256(rgb.tobytes() + depth.tobytes()).hexdigest())\n"
    )
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=REPO, check=True)
    assert out.stdout.strip() == _digest(small.render(77))


def test_poses_are_rigid_and_smooth(small: SyntheticScene) -> None:
    P = small.poses()
    assert P.shape == (540, 4, 4)
    for T in P:
        R = T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.array_equal(T[3], [0, 0, 0, 1])
        assert np.all(np.abs(T[:3, 3] - ROOM.centre()) < ROOM.half() - 0.5)
    fps = 30.0
    speed = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1) * fps
    assert 0.25 < speed.min() and speed.max() < 0.55
    rot = np.array([Rotation.from_matrix(P[i, :3, :3].T @ P[i + 1, :3, :3]).magnitude() for i in range(len(P) - 1)])
    assert np.degrees(rot.max()) * fps < 60.0
    # Smooth: accelerations are small (no jumps).
    acc = np.linalg.norm(np.diff(P[:, :3, 3], 2, axis=0), axis=1) * fps * fps
    assert acc.max() < 1.0
    # Optical convention: the camera's y axis (down) points roughly at the floor.
    assert np.all(P[:, 2, 1] < -0.9)
    # Frame i does not depend on the sequence length.
    assert np.array_equal(SyntheticScene(n_frames=10).pose(9), small.pose(9))
    with pytest.raises(IndexError):
        small.pose(540)


def test_stamps() -> None:
    s = SyntheticScene(n_frames=91)
    assert s.stamp_ns(0) == EPOCH_NS == 1_700_000_000 * 10**9
    assert s.stamp_ns(30) - s.stamp_ns(0) == 1_000_000_000
    assert s.stamp_ns(1) - s.stamp_ns(0) == 33_333_333
    assert s.stamp_ns(2) - s.stamp_ns(0) == 66_666_667
    frames = list(SyntheticScene(n_frames=3, width=32, height=24).frames())
    assert [f.stamp_ns for f in frames] == [s.stamp_ns(i) for i in range(3)]
    assert [f.seq for f in frames] == [0, 1, 2]


def test_groundtruth_tum_round_trip() -> None:
    s = SyntheticScene(n_frames=120)
    lines = [ln for ln in s.groundtruth_tum().splitlines() if ln and not ln.startswith("#")]
    assert len(lines) == 120
    for i, ln in enumerate(lines):
        parts = ln.split()
        assert len(parts) == 8 and len(parts[0].split(".")[1]) == 9
        assert int(Decimal(parts[0]) * 10**9) == s.stamp_ns(i)
        vals = np.array([float(x) for x in parts[1:]])
        T = pose_to_matrix(vals[:3], vals[3:])
        assert np.allclose(T, s.pose(i), atol=1e-8)
        assert math.isclose(np.linalg.norm(vals[3:]), 1.0, abs_tol=1e-8)


def test_turns_motion_is_fast_head_turns_on_the_same_walk() -> None:
    """motion=turns: the fast-motion development case turns at 150-210 deg/s at its peaks, smoothly,
    on the walk of the default path (same positions)."""
    fps = 30.0
    walk, turns = SyntheticScene(n_frames=180), SyntheticScene(n_frames=180, motion="turns")
    assert np.array_equal(walk.poses()[:, :3, 3], turns.poses()[:, :3, 3])
    R = turns.poses()[:, :3, :3]
    rate = np.degrees([Rotation.from_matrix(R[i].T @ R[i + 1]).magnitude() for i in range(len(R) - 1)]) * fps
    assert 150.0 < rate.max() < 215.0
    assert np.mean(rate > 100.0) > 0.2  # a good part of the time, not one spike
    assert np.abs(np.diff(rate)).max() < 40.0  # deg/s per frame: a smooth start and stop, no jump
    with pytest.raises(ValueError, match="motion"):
        SyntheticScene(n_frames=2, motion="spin")


def test_a_second_session_walks_the_loop_from_elsewhere_and_the_other_way_round() -> None:
    """start=S, reverse=1 (bench/localize.py's second sessions): the same loop, entered S s along
    it and walked backwards: frame i stands where the forward walk stood at S - i/fps, and looks
    where it goes and towards the pillar (the room's centre), as the forward walk does."""
    from octolog.kit.errors import ConfigError
    from octolog.replay.sources import open_source
    from octolog.replay.synthetic_trajectory import camera_trajectory

    t = np.arange(0.0, 18.0, 0.25)
    forward, _ = camera_trajectory(5.0 - t)
    pos, rot = camera_trajectory(t, path_start_s=5.0, reverse=True)
    assert np.allclose(pos, forward, atol=1e-12)
    step = np.diff(pos, axis=0)
    assert np.all(np.einsum("ij,ij->i", rot[:-1, :, 2], step / np.linalg.norm(step, axis=1, keepdims=True)) > 0.5)
    inward = -pos[:, :2] / np.linalg.norm(pos[:, :2], axis=1, keepdims=True)
    assert np.mean(np.einsum("ij,ij->i", rot[:, :2, 2], inward) > 0.0) > 0.9
    src = open_source("synthetic:10:start=5:reverse=1")
    frame3, _ = camera_trajectory(np.array([3 / 30.0]), path_start_s=5.0, reverse=True)
    assert src.name == "synthetic:10:start=5:reverse=1" and np.allclose(src.scene.pose(3)[:3, 3], frame3[0])
    with pytest.raises(ConfigError, match="synthetic"):
        open_source("synthetic:10:reverse=2")


def test_exposure_blurs_colour_along_the_turn_only() -> None:
    """exposure=MS smears colour by the camera's rotation over the exposure: a frame mid-turn loses
    most of its fine detail, a frame of the plain walk little, depth is untouched."""
    def sharpness(img: np.ndarray) -> float:
        g = img.mean(axis=2)
        return float(np.abs(np.diff(g, axis=1)).mean())

    i = 11  # the first turn at its fastest (0.375 s)
    sharp = SyntheticScene(n_frames=20, width=320, height=240, motion="turns").render(i)
    blurred = SyntheticScene(n_frames=20, width=320, height=240, motion="turns", exposure_ms=8.0).render(i)
    assert sharpness(blurred.rgb) < 0.5 * sharpness(sharp.rgb)  # ~7 px of smear at 320 px wide
    assert np.array_equal(blurred.depth, sharp.depth)
    still = SyntheticScene(n_frames=20, width=320, height=240).render(i)
    still_blurred = SyntheticScene(n_frames=20, width=320, height=240, exposure_ms=8.0).render(i)
    assert sharpness(still_blurred.rgb) > 0.75 * sharpness(still.rgb)  # the walk turns at under 50 deg/s
    with pytest.raises(ValueError, match="exposure_ms"):
        SyntheticScene(n_frames=2, exposure_ms=50.0)  # longer than a frame at 30 fps


def test_the_texture_atlas_from_the_cache_is_the_baked_one_and_a_broken_file_is_baked_again(tmp_path, monkeypatch):
    """The room's textures are kept in octolog's cache (octolog.kit.cache): what comes back is the
    bake, bit for bit, and a truncated cache file is baked again and replaced, never read as data."""
    from octolog.replay import synthetic_textures as st

    monkeypatch.setenv("OCTOLOG_CACHE", str(tmp_path))
    fields = ("atlas", "origin", "limit", "coef", "normal")
    baked = st._bake(3, 0.02, 2)
    st.scene_textures.cache_clear()
    first = st.scene_textures(3, 0.02, 2)  # baked and kept
    (kept,) = (tmp_path / "synthetic").glob("textures-*.npz")
    st.scene_textures.cache_clear()
    again = st.scene_textures(3, 0.02, 2)  # from the file
    for got in (first, again):
        for name in fields:
            a, b = getattr(got, name), getattr(baked, name)
            assert a.dtype == b.dtype and np.array_equal(a, b), name
    kept.write_bytes(kept.read_bytes()[:1000])
    st.scene_textures.cache_clear()
    assert np.array_equal(st.scene_textures(3, 0.02, 2).atlas, baked.atlas)
    assert kept.stat().st_size > 1000  # replaced whole
    st.scene_textures.cache_clear()


def test_a_frame_from_the_cache_is_the_rendered_one_and_a_broken_file_is_rendered_again(tmp_path, monkeypatch):
    """Rendered frames are kept in octolog's cache: a scene of another length reads them back bit
    for bit (frame i does not depend on the length), another scene does not share them, and a
    truncated file is rendered again and replaced."""
    monkeypatch.setenv("OCTOLOG_CACHE", str(tmp_path))
    short = SyntheticScene(n_frames=10, width=160, height=120)
    rendered = short.render_frame(4)
    first = short.render(4)  # rendered and kept
    (folder,) = (tmp_path / "synthetic").glob("frames-*")
    (kept,) = folder.glob("*.npz")
    longer = SyntheticScene(n_frames=300, width=160, height=120)
    again = longer.render(4)  # from the file
    for got in (first, again):
        assert np.array_equal(got.rgb, rendered[0]) and np.array_equal(got.depth, rendered[1])
        assert got.seq == 4 and got.stamp_ns == short.stamp_ns(4)
    SyntheticScene(n_frames=10, width=160, height=120, seed=5).render(4)
    assert len(list((tmp_path / "synthetic").glob("frames-*"))) == 2  # a scene of its own
    kept.write_bytes(kept.read_bytes()[:1000])
    assert np.array_equal(SyntheticScene(n_frames=10, width=160, height=120).render(4).rgb, rendered[0])
    assert kept.stat().st_size > 1000  # replaced whole


def test_an_uncalibrated_imu_is_the_same_samples_turned_late_and_noisier() -> None:
    """`imurot`, `imudt`, `imunoise`: the development data of an IMU nobody calibrated. Against the
    calibrated IMU of the same room and draws, the turned and late one differs by exactly the turn of
    the motion measured earlier (bias and noise cancel); the noisier one's third differences (the
    noise, the motion all but gone) scale with the factor."""
    from octolog.replay.imu import source_imu
    from octolog.replay.sources import open_source
    from octolog.replay.synthetic_imu import mismatch_rotation, true_motion

    base = open_source("synthetic:90:imu=200")
    turned = open_source("synthetic:90:imu=200:imurot=5:imudt=10")
    noisier = open_source("synthetic:90:imu=200:imunoise=3")
    a, b, c = (source_imu(s).samples for s in (base, turned, noisier))
    assert turned.name == "synthetic:90:imu=200:imurot=5:imudt=10"
    R = mismatch_rotation(5.0)
    assert math.isclose(np.degrees(np.arccos((np.trace(R) - 1) / 2)), 5.0, rel_tol=1e-9)
    t = (a.stamp_ns - a.stamp_ns[0]) * 1e-9
    scene = base.scene
    w_now, f_now = true_motion(scene._trajectory, t)
    w_late, f_late = true_motion(scene._trajectory, t - 0.010)
    assert np.allclose(b.gyro - a.gyro, w_late @ R.T - w_now, atol=1e-9)
    assert np.allclose(b.accel - a.accel, f_late @ R.T - f_now, atol=1e-9)

    def spread(x: np.ndarray) -> float:
        return float(np.median(np.abs(x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3])))
    assert 2.7 < spread(c.gyro) / spread(a.gyro) < 3.3
    assert 2.7 < spread(c.accel) / spread(a.accel) < 3.3
    with pytest.raises(Exception, match="synthetic"):
        open_source("synthetic:90:imu=200:imunoise=0")


def test_people_stand_in_front_of_the_room_while_there_and_nowhere_else() -> None:
    from octolog.replay import synthetic_people

    people = SyntheticScene(n_frames=240, width=160, height=120, people="stand")
    twin = SyntheticScene(n_frames=240, width=160, height=120)
    K = people.intrinsics
    i = 75  # 2.5 s: the person stands in view
    depth, depth0 = people.render_frame(i)[1], twin.render_frame(i)[1]
    moved = depth != depth0
    assert moved.mean() > 0.01
    assert np.all(depth[moved] < depth0[moved])  # a person only ever hides the room
    v, u = np.nonzero(moved)
    z = depth[moved] * people.depth_scale_m
    cam = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], 1)
    T = people.pose(i)
    world = cam @ T[:3, :3].T + T[:3, 3]
    assert synthetic_people.inside(people.people, i / 30.0, world, margin_m=0.01).all()  # on the person
    late = 210  # 7 s: gone through the door
    assert np.array_equal(people.render_frame(late)[1], twin.render_frame(late)[1])
    assert np.array_equal(people.render_frame(late)[0], twin.render_frame(late)[0])
