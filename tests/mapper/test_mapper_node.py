"""The mapper follows pose corrections exactly, refuses bad keyframes, and serves late joiners."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT, free_port

from octolog.kit.errors import InputError
from octolog.kit.geometry import pose_to_matrix
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import make_mapper
from octolog.replay.synthetic import SyntheticScene


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    return SyntheticScene(n_frames=40, width=320, height=240)


def _keyframes(scene: SyntheticScene) -> list[tuple[int, np.ndarray, object]]:
    return [(k, scene.pose(i), scene.render(i)) for k, i in enumerate(range(0, 40, 8))]


def _bytes(mapper, tmp_path, name: str) -> tuple[bytes, bytes]:
    files = mapper.write(tmp_path / name)
    return (tmp_path / name / "map.bt").read_bytes(), (tmp_path / name / "cloud.ply").read_bytes()


def _drifted(T: np.ndarray, k: int) -> np.ndarray:
    d = pose_to_matrix(np.array([0.03 * k, -0.02 * k, 0.01 * k]), np.array([0.0, 0.0, np.sin(0.01 * k), np.cos(0.01 * k)]))
    return d @ T


def test_corrected_map_equals_map_built_with_corrected_poses(scene, tmp_path):
    kfs = _keyframes(scene)
    moved = make_mapper(MapperConfig())
    for k, T, f in kfs:
        moved.integrate(k, _drifted(T, k), f)
    drifted_bt, _ = _bytes(moved, tmp_path, "drifted")
    assert moved.correct({k: T for k, T, _ in kfs}) == len(kfs) - 1  # keyframe 0 had no drift
    scratch = make_mapper(MapperConfig())
    for k, T, f in kfs:
        scratch.integrate(k, T, f)
    assert _bytes(moved, tmp_path, "moved") == _bytes(scratch, tmp_path, "scratch")
    assert drifted_bt != _bytes(scratch, tmp_path, "scratch2")[0]  # the correction did change the map


def test_corrections_between_looks_cost_one_rebuild_and_change_no_byte(scene, tmp_path):
    # a live session closes loops faster than it looks at the map: each correction marks the map
    # stale, the next look (snapshot, files) rebuilds it once, keyframes arriving meanwhile included
    kfs = _keyframes(scene)
    lazy = make_mapper(MapperConfig())
    for k, T, f in kfs[:3]:
        lazy.integrate(k, _drifted(T, k), f)
    assert lazy.correct({k: _drifted(T, k + 1) for k, T, _ in kfs[:3]}) == 3
    assert lazy.correct({k: T for k, T, _ in kfs[:3]}) == 3
    for k, T, f in kfs[3:]:
        lazy.integrate(k, T, f)
    assert lazy.rebuilds == 0
    scratch = make_mapper(MapperConfig())
    for k, T, f in kfs:
        scratch.integrate(k, T, f)
    assert _bytes(lazy, tmp_path, "lazy") == _bytes(scratch, tmp_path, "scratch")
    assert lazy.rebuilds == 1 and scratch.rebuilds == 0
    assert lazy.octree.bt_bytes() == scratch.octree.bt_bytes() and lazy.rebuilds == 1  # fresh now


def _shifted(T: np.ndarray, metres: float) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += metres
    return out


def test_a_snapshot_reintegrates_from_the_first_keyframe_moved_beyond_the_tolerance(scene, tmp_path):
    """While the session runs a correction that moves keyframes less than `move_tolerance_voxels` at
    every point leaves their voxels where they went in (the cloud moves exactly); one that moves a
    keyframe farther re-integrates from the checkpoint before it (every CHECKPOINT_EVERY keyframes),
    at the current poses. The files are the exact map of the final poses either way."""
    from octolog.mapper.core import CHECKPOINT_EVERY

    n = 2 * CHECKPOINT_EVERY + 5
    frames = [(k, scene.pose(k), scene.render(k)) for k in range(n)]
    tiny, far = 0.003, 0.05  # m: below and above a quarter of the 5 cm voxel
    live = make_mapper(MapperConfig())
    for k, T, f in frames:
        live.integrate(k, T, f)

    def scratch(poses: list[np.ndarray], cfg: MapperConfig = MapperConfig()):
        m = make_mapper(cfg)
        for (k, _, f), T in zip(frames, poses):
            m.integrate(k, T, f)
        return m

    original = [T for _, T, _ in frames]
    nudged = [_shifted(T, tiny) for T in original]
    before = live.octree.bt_bytes()
    live.correct(dict(enumerate(nudged)))
    assert live.octree.bt_bytes() == before and live.rebuilds == 0  # no voxel moved
    assert np.array_equal(live.cloud.cloud()[0], scratch(nudged).cloud.cloud()[0])  # the cloud did
    assert scratch(nudged).octree.bt_bytes() != before  # (the nudge does move voxels when it counts)
    late = 2 * CHECKPOINT_EVERY + 2
    final = nudged[:late] + [_shifted(T, far) for T in nudged[late:]]
    live.correct(dict(enumerate(final)))
    # from the checkpoint at 2 * CHECKPOINT_EVERY keyframes: those before it keep their voxels
    kept = original[:2 * CHECKPOINT_EVERY] + final[2 * CHECKPOINT_EVERY:]
    assert live.octree.bt_bytes() == scratch(kept).octree.bt_bytes() and live.rebuilds == 1
    exact = scratch(final)
    assert _bytes(live, tmp_path, "live") == _bytes(exact, tmp_path, "exact")
    # with no tolerance every snapshot is the exact map
    strict = scratch(original, MapperConfig(move_tolerance_voxels=0))
    strict.correct(dict(enumerate(nudged)))
    assert strict.octree.bt_bytes() == scratch(nudged).octree.bt_bytes()


@pytest.mark.parametrize(
    ("pose", "depth_zero", "message"),
    [
        (np.full((4, 4), np.nan), False, "not a finite 4x4"),
        (pose_to_matrix(np.array([5000.0, 0, 0]), np.array([0, 0, 0, 1.0])), False, "outside the map bounds"),
        (np.eye(4), True, "no valid depth"),
    ],
)
def test_bad_keyframes_are_refused_and_leave_the_map_alone(scene, tmp_path, pose, depth_zero, message):
    m = make_mapper(MapperConfig())
    k, T, f = _keyframes(scene)[0]
    m.integrate(k, T, f)
    before = m.octree.bt_bytes()
    k2, _, f2 = _keyframes(scene)[1]
    if depth_zero:
        f2 = type(f2)(f2.seq, f2.stamp_ns, f2.rgb, np.zeros_like(f2.depth), f2.depth_scale_m, f2.intrinsics)
    with pytest.raises(InputError, match=message):
        m.integrate(k2, pose, f2)
    assert m.octree.bt_bytes() == before and list(m.keyframes) == [k]



def test_mapper_process_follows_corrections_and_serves_late_joiners(scene, tmp_path):
    """The real `octolog map` process; this test plays the tracker over a real Zenoh link."""
    from octolog.kit.bus import Bus, BusConfig
    from octolog.schemas import posemsgs, rgbdmsgs, streammsgs
    from octolog.schemas.topics import KEYFRAME, KEYFRAME_END, KEYFRAME_POSES, MAP_UPDATE, OCTOMAP

    ep = f"tcp/127.0.0.1:{free_port()}"
    kfs = _keyframes(scene)
    proc = subprocess.Popen([sys.executable, "-m", "octolog", "map", "--connect", ep, "--no-multicast",
                             "--out", str(tmp_path / "map"), "--set", "publish_every=1"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with Bus(BusConfig(listen=(ep,), multicast_scouting=False), "tracker") as bus:
            bus.subscribe([MAP_UPDATE, OCTOMAP])
            bus.announce()
            bus.watch(["mapper"])
            bus.wait_for(["mapper"], timeout_s=60)
            pub_kf, pub_poses, pub_end = bus.publisher(KEYFRAME), bus.publisher(KEYFRAME_POSES), bus.publisher(KEYFRAME_END)
            for k, T, f in kfs:
                pub_kf.put(rgbdmsgs.keyframe_msg(k, _drifted(T, k), f))
            updates = octomaps = 0
            deadline = time.monotonic() + 120
            while (updates < len(kfs) or octomaps < len(kfs)) and time.monotonic() < deadline:
                r = bus.receive(timeout_s=1.0)
                updates += r is not None and r.topic == MAP_UPDATE
                octomaps += r is not None and r.topic == OCTOMAP
            assert updates == octomaps == len(kfs)
            # a late joiner asks for the current map
            with Bus(BusConfig(connect=(ep,), multicast_scouting=False), "viewer") as late:
                from octolog.mapper.node import fetch_map

                got = fetch_map(late, timeout_s=20)
                from octolog.schemas.topics import MAP_SAVE

                saved = late.fetch(MAP_SAVE, timeout_s=30)  # "write the files now"
            assert got is not None and got.binary and got.resolution == pytest.approx(0.05) and len(got.data) > 100
            assert saved is not None and (tmp_path / "map" / "map.bt").exists()
            assert json.loads(saved.data)["bt"] == str(tmp_path / "map" / "map.bt")
            pub_poses.put(posemsgs.keyframe_poses_msg({k: T for k, T, _ in kfs}))
            pub_end.put(streammsgs.stream_end_msg(KEYFRAME.name, pub_kf.count))
            out, err = proc.communicate(timeout=120)
            assert proc.returncode == 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
    scratch = make_mapper(MapperConfig())
    for k, T, f in kfs:
        scratch.integrate(k, T, f)
    assert (tmp_path / "map" / "map.bt").read_bytes() == _bytes(scratch, tmp_path, "scratch")[0]
    assert "5 keyframes (0 skipped)" in out


def test_pcd_and_ply_read_back_in_open3d(scene, tmp_path):
    import open3d as o3d

    m = make_mapper(MapperConfig())
    k, T, f = _keyframes(scene)[0]
    m.integrate(k, T, f)
    files = m.write(tmp_path)
    pts, cols = m.map_cloud()
    assert len(pts) > 1000
    for key in ("ply", "pcd"):
        pc = o3d.io.read_point_cloud(files[key])
        np.testing.assert_allclose(np.asarray(pc.points), pts.astype(np.float32), atol=1e-6)
        np.testing.assert_allclose(np.asarray(pc.colors) * 255, cols, atol=0.5)


def test_map_files_are_described_and_damage_is_named(scene, tmp_path):
    from helpers import octolog as cli

    m = make_mapper(MapperConfig())
    for k, T, f in _keyframes(scene)[:2]:
        m.integrate(k, T, f)
    files = m.write(tmp_path)
    for key, kind in (("bt", "OcTree"), ("ot", "ColorOcTree")):
        out = cli("info", files[key]).stdout
        assert f"OctoMap {kind}, resolution 0.05 m" in out and "occupied" in out
        data = Path(files[key]).read_bytes()
        cut = tmp_path / f"cut.{key}"
        cut.write_bytes(data[: len(data) // 2])
        proc = cli("info", str(cut), check=False)
        assert proc.returncode == 1 and f"{cut}: truncated or corrupt OctoMap file" in proc.stderr
    junk = tmp_path / "junk.bt"
    junk.write_text("hello\n")
    proc = cli("info", str(junk), check=False)
    assert proc.returncode == 1 and "not an OctoMap file" in proc.stderr
