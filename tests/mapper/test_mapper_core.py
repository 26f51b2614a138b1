"""Mapper core: back-projection, the two filter layers, dense cloud, PLY, occupancy octree, .bt.

Synthetic data only (a wall, a box in front of it); no ../shared needed.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from octolog.kit.errors import MapError
from octolog.kit.geometry import Intrinsics, RgbdFrame, pose_to_matrix
from octolog.mapper.cloud import (
    DenseCloud,
    backproject,
    keyframe_cloud,
    statistical_outlier_removal,
    transform,
    voxel_downsample,
    write_ply,
)
from octolog.mapper.config import MapperConfig
from octolog.mapper.core import Mapper
from octolog.mapper.octree import OccupancyOctree
from octolog.mapper.sensor_model import SensorModel

K = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
SCALE = 0.001  # 1 mm per depth unit


def wall_frame(depth_m: float = 2.0, h: int = 480, w: int = 640) -> tuple[np.ndarray, np.ndarray]:
    """A fronto-parallel wall at `depth_m` filling the image, with a colour gradient."""
    depth = np.full((h, w), int(round(depth_m / SCALE)), dtype=np.uint16)
    rgb = np.zeros((h, w, 3), dtype=np.uint8)
    rgb[..., 0] = (np.arange(w) * 255 // (w - 1))[None, :]
    rgb[..., 1] = (np.arange(h) * 255 // (h - 1))[:, None]
    rgb[..., 2] = 77
    return depth, rgb


def scene_frame(seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Wall at 2.5 m, a box at 1.2 m, 1 mm depth noise, holes and flying pixels (seeded)."""
    rng = np.random.default_rng(seed)
    depth, rgb = wall_frame(2.5)
    depth[150:330, 220:420] = 1200
    depth = (depth.astype(np.int32) + rng.integers(-2, 3, depth.shape)).astype(np.uint16)
    depth[rng.random(depth.shape) < 0.02] = 0  # holes
    fly = rng.random(depth.shape) < 0.001  # flying pixels between box and wall
    depth[fly] = rng.integers(1300, 2400, int(fly.sum())).astype(np.uint16)
    return depth, rgb


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    return np.floor(points / voxel).astype(np.int64)


# ---- back-projection ----------------------------------------------------------------------------


def test_backproject_wall_at_known_depth():
    depth, rgb = wall_frame(2.0)
    depth[0, 0] = 0  # no reading
    depth[1, 1] = 5000  # 5 m: beyond the 4 m default range
    pts, col = backproject(depth, rgb, K, SCALE)
    assert pts.dtype == np.float64 and col.dtype == np.uint8
    assert pts.shape == (480 * 640 - 2, 3) and col.shape == pts.shape
    assert np.all(pts[:, 2] == 2.0)
    # Pinhole geometry: pixel (u, v) = (639, 479) is the last point.
    assert pts[-1, 0] == pytest.approx((639 - K.cx) * 2.0 / K.fx)
    assert pts[-1, 1] == pytest.approx((479 - K.cy) * 2.0 / K.fy)
    assert np.array_equal(col[-1], rgb[479, 639])
    # Stride keeps full-image pixel coordinates.
    pts2, _ = backproject(depth, rgb, K, SCALE, stride=2)
    assert pts2.shape[0] == 240 * 320 - 1  # (0,0) is a hole, (1,1) is skipped by the stride
    assert pts2[0, 0] == pytest.approx((2 - K.cx) * 2.0 / K.fx)  # first valid: (u, v) = (2, 0)
    # Range limit.
    pts3, _ = backproject(depth, rgb, K, SCALE, max_range_m=1.5)
    assert pts3.shape[0] == 0


@pytest.mark.parametrize(
    "bad",
    [
        dict(depth=np.zeros((480, 640), np.float32)),
        dict(rgb=np.zeros((480, 640, 3), np.float32)),
        dict(rgb=np.zeros((240, 320, 3), np.uint8)),
        dict(intrinsics=Intrinsics(320, 240, 262.5, 262.5, 159.5, 119.5)),
        dict(depth_scale_m=float("nan")),
        dict(stride=0),
    ],
)
def test_backproject_rejects_bad_inputs(bad):
    depth, rgb = wall_frame()
    args = dict(depth=depth, rgb=rgb, intrinsics=K, depth_scale_m=SCALE) | bad
    with pytest.raises(MapError):
        backproject(args.pop("depth"), args.pop("rgb"), args.pop("intrinsics"), args.pop("depth_scale_m"), **args)


# ---- filters ------------------------------------------------------------------------------------


def test_sor_removes_far_outliers_and_keeps_the_wall():
    depth, rgb = wall_frame(2.0)
    wall, wall_col = backproject(depth, rgb, K, SCALE, stride=4)
    rng = np.random.default_rng(1)
    outliers = rng.uniform([-1.0, -1.0, 0.3], [1.0, 1.0, 1.7], size=(60, 3))
    pts = np.concatenate([wall, outliers])
    col = np.concatenate([wall_col, np.full((60, 3), 255, np.uint8)])
    kept, kept_col = statistical_outlier_removal(pts, col, nb_neighbors=20, std_ratio=2.0)
    assert not np.any(kept[:, 2] < 1.9), "an injected outlier survived"
    assert kept.shape[0] >= 0.95 * wall.shape[0]
    assert kept_col.shape == kept.shape
    # Kept points are input points, in input order.
    index = {row.tobytes(): i for i, row in enumerate(pts)}
    order = [index[row.tobytes()] for row in kept]
    assert order == sorted(order)
    assert np.array_equal(kept_col, col[order])


def test_voxel_downsample_one_point_per_voxel():
    rng = np.random.default_rng(2)
    pts = rng.uniform(0.0, 0.1, size=(100_000, 3))
    col = rng.integers(0, 256, size=pts.shape).astype(np.uint8)
    out, out_col = voxel_downsample(pts, col, 0.01)
    assert out.shape[0] <= 1000 and out_col.shape == out.shape
    keys = voxel_keys(out, 0.01)
    assert np.unique(keys, axis=0).shape[0] == out.shape[0]
    # Sorted by voxel index, and every output point lies in a voxel that had input points.
    assert np.array_equal(keys, keys[np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))])
    assert set(map(tuple, keys)) <= set(map(tuple, voxel_keys(pts, 0.01)))
    # Colour is the mean of the voxel's colours (uniform random -> close to 127.5).
    assert abs(out_col.astype(float).mean() - 127.5) < 2.0


def test_voxel_downsample_is_the_mean():
    pts = np.array([[0.001, 0.001, 0.001], [0.003, 0.005, 0.007], [0.5, 0.5, 0.5]])
    col = np.array([[0, 10, 255], [10, 20, 254], [1, 2, 3]], np.uint8)
    out, out_col = voxel_downsample(pts, col, 0.01)
    assert np.allclose(out, [[0.002, 0.003, 0.004], [0.5, 0.5, 0.5]])
    assert out_col.tolist() == [[5, 15, 254], [1, 2, 3]]  # rint(254.5) == 254 (round half even)


def test_filters_reject_bad_inputs():
    with pytest.raises(MapError):
        voxel_downsample(np.zeros((5, 2)), np.zeros((5, 2), np.uint8))
    with pytest.raises(MapError):
        voxel_downsample(np.full((5, 3), np.nan), np.zeros((5, 3), np.uint8))
    with pytest.raises(MapError):
        statistical_outlier_removal(np.zeros((5, 3)), np.zeros((4, 3), np.uint8))
    with pytest.raises(MapError):
        voxel_downsample(np.zeros((5, 3)), np.zeros((5, 3), np.uint8), voxel_m=0.0)


def test_transform_and_bad_pose():
    T = pose_to_matrix(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]))
    out = transform(np.array([[1.0, 0.0, 0.0]]), T)  # 90 deg about z: x -> y
    assert np.allclose(out, [[1.0, 3.0, 3.0]])
    bad = T.copy()
    bad[0, 3] = np.nan
    with pytest.raises(MapError):
        transform(np.zeros((1, 3)), bad)
    with pytest.raises(MapError):
        transform(np.zeros((1, 3)), np.eye(3))


def test_keyframe_cloud_every_filter_drops_flying_pixels():
    depth, rgb = scene_frame()
    for outliers, sor_first in (("image", False), ("knn", False), ("knn", True)):
        pts, col = keyframe_cloud(depth, rgb, K, SCALE, np.eye(4), sor_first=sor_first, outliers=outliers)
        keys = voxel_keys(pts, 0.01)
        assert np.unique(keys, axis=0).shape[0] == pts.shape[0]
        z = pts[:, 2]
        on_surface = (np.abs(z - 1.2) < 0.02) | (np.abs(z - 2.5) < 0.02)
        assert on_surface.mean() > 0.995


def test_image_outlier_filter_drops_flying_pixels_and_keeps_far_surfaces():
    """The image-grid filter: the unfiltered cloud holds the flying pixels, the filtered one almost
    none, and a far surface (4x the pixel spacing of a near one) is kept as whole as a near one: the
    distance is measured in pixel footprints, not metres. Deterministic to the byte."""
    from octolog.mapper.cloud import image_outlier_removal

    depth, rgb = scene_frame()
    raw, _ = backproject(depth, rgb, K, SCALE, stride=2)
    kept, _ = image_outlier_removal(depth, rgb, K, SCALE, stride=2)

    def off_surface(p: np.ndarray) -> int:
        return int((~((np.abs(p[:, 2] - 1.2) < 0.02) | (np.abs(p[:, 2] - 2.5) < 0.02))).sum())

    assert off_surface(raw) > 50 and off_surface(kept) < 0.1 * off_surface(raw)
    assert len(kept) > 0.95 * (len(raw) - off_surface(raw))  # the surfaces stay
    near, far = wall_frame(0.8), wall_frame(3.6)
    for d, c in (near, far):
        noisy = (d.astype(np.int32) + np.random.default_rng(1).integers(-3, 4, d.shape)).astype(np.uint16)
        n_raw = len(backproject(noisy, c, K, SCALE, stride=2)[0])
        assert len(image_outlier_removal(noisy, c, K, SCALE, stride=2)[0]) > 0.97 * n_raw
    again, _ = image_outlier_removal(depth, rgb, K, SCALE, stride=2)
    assert again.tobytes() == kept.tobytes()


# ---- dense cloud and PLY ------------------------------------------------------------------------


def test_dense_cloud_replaces_a_keyframe_and_ignores_arrival_order():
    depth, rgb = wall_frame(2.0)
    p, c = keyframe_cloud(depth, rgb, K, SCALE, np.eye(4))
    shifted = pose_to_matrix(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    a = DenseCloud()
    a.add(1, p, c)
    a.add(2, transform(p, shifted), c)
    b = DenseCloud()
    b.add(2, transform(p, shifted), c)
    b.add(1, p, c)
    pa, ca = a.cloud()
    pb, cb = b.cloud()
    assert pa.tobytes() == pb.tobytes() and ca.tobytes() == cb.tobytes()
    assert set(np.round(pa[:, 2], 3)) == {2.0, 3.0}
    # Pose correction: keyframe 2 re-added at the wall itself -> everything at z = 2.
    a.add(2, p, c)
    pa2, _ = a.cloud()
    assert np.allclose(pa2[:, 2], 2.0) and pa2.shape[0] == voxel_downsample(p, c)[0].shape[0]
    assert a.keyframe_ids() == [1, 2]
    empty = DenseCloud().cloud()
    assert empty[0].shape == (0, 3) and empty[1].dtype == np.uint8


def test_a_depth_bias_correction_puts_a_biased_wall_back_in_place():
    """A wall 3.5 m away read 1 % short (what an inverse offset of 0.00289 1/m does): with the
    keyframe's depth_inverse_offset at that value, the keyframe cloud is back at 3.5 m (one depth
    unit), every point moved along its ray; without it, 3.5 cm short."""
    beta, z = 0.01 / 3.5, 3.5
    depth, rgb = wall_frame(z / (1 + beta * z))  # what the biased camera reads
    short, _ = keyframe_cloud(depth, rgb, K, SCALE, np.eye(4))
    fixed, _ = keyframe_cloud(depth, rgb, K, SCALE, np.eye(4), inverse_offset=beta)
    assert abs(float(np.median(short[:, 2])) - (z - 0.035)) < 0.002
    assert abs(float(np.median(fixed[:, 2])) - z) < 0.002
    # along the ray: the image position of each point stays where it was
    u_short = short[:, 0] / short[:, 2]
    assert np.allclose(np.sort(fixed[:, 0] / fixed[:, 2])[[0, -1]], np.sort(u_short)[[0, -1]], atol=0.01)


def test_ply_round_trip_through_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    depth, rgb = scene_frame()
    p, c = keyframe_cloud(depth, rgb, K, SCALE, np.eye(4))
    path = tmp_path / "cloud.ply"
    write_ply(path, p, c)
    pc = o3d.io.read_point_cloud(str(path))
    assert np.array_equal(np.asarray(pc.points), p.astype(np.float32).astype(np.float64))
    assert np.array_equal(np.rint(np.asarray(pc.colors) * 255).astype(np.uint8), c)
    assert not list(tmp_path.glob("*.tmp"))


def test_write_ply_unwritable_path(tmp_path):
    with pytest.raises(MapError, match="cannot write"):
        write_ply(tmp_path / "missing-dir" / "x.ply", np.zeros((1, 3)), np.zeros((1, 3), np.uint8))


# ---- occupancy octree ---------------------------------------------------------------------------


def wall_octree() -> tuple[OccupancyOctree, np.ndarray]:
    """A 1 m x 1 m wall at z = 2.02 m (mid-voxel at 5 cm) seen from the origin."""
    g = np.arange(-0.5, 0.5, 0.01)
    xs, ys = np.meshgrid(g, g)
    wall = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.02)], axis=1)
    tree = OccupancyOctree(0.05)
    tree.insert(wall, np.zeros(3))
    return tree, wall


def test_octree_sensor_model_is_set():
    t = OccupancyOctree().tree
    assert t.getResolution() == 0.05
    assert t.getProbHit() == pytest.approx(0.7)
    assert t.getProbMiss() == pytest.approx(0.4)
    assert t.getClampingThresMin() == pytest.approx(0.12)
    assert t.getClampingThresMax() == pytest.approx(0.97)


def test_octree_wall_occupied_free_unknown():
    tree, _ = wall_octree()
    occupied = np.array([[0.0, 0.0, 2.02], [0.3, -0.2, 2.02], [-0.45, 0.45, 2.02]])
    free = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.0], [0.1, 0.1, 1.9], [0.2, -0.2, 1.5]])
    unknown = np.array([[0.0, 0.0, 2.2], [0.0, 0.0, 3.0], [0.0, 1.5, 1.0], [0.0, 0.0, -1.0]])
    assert tree.classify(occupied).tolist() == [1, 1, 1]
    assert tree.classify(free).tolist() == [0, 0, 0, 0]
    assert tree.classify(unknown).tolist() == [-1, -1, -1, -1]
    occ = tree.occupied_centres()
    assert occ.shape == (20 * 20, 3)  # a 1 m x 1 m wall at 5 cm
    assert np.allclose(occ[:, 2], 2.025)
    assert np.all(tree.free_centres()[:, 2] < 2.0)
    s = tree.stats()
    assert s["occupied_voxels"] == 400 and s["free_voxels"] > 400
    assert s["known_volume_m3"] == pytest.approx((s["occupied_voxels"] + s["free_voxels"]) * 0.05**3)
    assert s["memory_bytes"] > 0 and s["resolution_m"] == 0.05


def test_octree_max_range_only_clears():
    g = np.arange(-0.5, 0.5, 0.01)
    xs, ys = np.meshgrid(g, g)
    wall = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.02)], axis=1)
    tree = OccupancyOctree(0.05)
    tree.insert(wall, np.zeros(3), max_range_m=1.0)
    assert tree.occupied_centres().shape[0] == 0
    assert tree.classify(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.5]])).tolist() == [0, -1]


def test_write_bt_keeps_the_probabilistic_tree(tmp_path):
    tree, wall = wall_octree()
    probe = np.array([0.0, 0.0, 2.02])
    before = tree.tree.search(probe).getLogOdds()
    assert before == pytest.approx(np.log(0.7 / 0.3), rel=1e-5)
    tree.write_bt(tmp_path / "a.bt")
    assert tree.tree.search(probe).getLogOdds() == before  # not max-likelihood'ed in place
    tree.insert(wall, np.zeros(3))
    assert tree.tree.search(probe).getLogOdds() == pytest.approx(2 * before, rel=1e-5)


def _other_binding_voxels(path: Path, resolution: float) -> tuple[np.ndarray, int]:
    """Occupied voxel centres (expanded to full resolution, sorted) and free voxel count via octomap-python."""
    octomap = pytest.importorskip("octomap")
    t = octomap.OcTree(resolution)
    assert t.readBinary(str(path).encode())
    idx = []
    free = 0
    for it in t.begin_leafs():
        size = it.getSize()
        w = int(round(size / resolution))
        if not t.isNodeOccupied(it):
            free += w**3
            continue
        first = np.rint(np.asarray(it.getCoordinate(), float) / resolution - w / 2.0).astype(np.int64)
        g = np.arange(w)
        off = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        idx.append(first + off)
    idx = np.concatenate(idx)
    idx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
    return (idx + 0.5) * resolution, free


def test_bt_is_read_by_the_other_binding(tmp_path):
    depth, rgb = scene_frame()
    T = pose_to_matrix(np.array([0.1, -0.2, 0.3]), np.array([0.0, 0.0871557, 0.0, 0.9961947]))
    p, _ = keyframe_cloud(depth, rgb, K, SCALE, T)
    tree = OccupancyOctree(0.05)
    tree.insert(p, T[:3, 3])
    path = tmp_path / "map.bt"
    tree.write_bt(path)
    assert path.read_bytes().startswith(b"# Octomap OcTree binary file\n")
    occ, free = _other_binding_voxels(path, 0.05)
    mine = tree.occupied_centres()
    assert mine.shape[0] > 1000
    assert np.array_equal(occ, mine)
    assert free == tree.stats()["free_voxels"]


def test_empty_octree_writes_a_valid_bt(tmp_path):
    octomap = pytest.importorskip("octomap")
    tree = OccupancyOctree()
    tree.write_bt(tmp_path / "empty.bt")
    other = octomap.OcTree(0.05)
    assert other.readBinary(str(tmp_path / "empty.bt").encode()) and other.size() == 0
    assert tree.occupied_centres().shape == (0, 3) and tree.stats()["known_volume_m3"] == 0.0


def test_octree_rejects_bad_inputs(tmp_path):
    tree = OccupancyOctree()
    with pytest.raises(MapError):
        tree.insert(np.zeros((4, 2)), np.zeros(3))
    with pytest.raises(MapError):
        tree.insert(np.zeros((4, 3)), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(MapError):
        tree.insert(np.full((4, 3), np.inf), np.zeros(3))
    with pytest.raises(MapError):
        tree.insert(np.full((4, 3), 5000.0), np.zeros(3))  # beyond the tree's +/-1638 m cube
    with pytest.raises(MapError):
        OccupancyOctree(0.0)
    with pytest.raises(MapError):
        OccupancyOctree(model=SensorModel(prob_hit=0.4))
    with pytest.raises(MapError, match="cannot write"):
        tree.write_bt(tmp_path / "missing-dir" / "x.bt")
    assert tree.insert(np.zeros((0, 3)), np.zeros(3)) == 0


# ---- determinism --------------------------------------------------------------------------------

_BUILD_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    sys.path.insert(0, {tests_dir!r})
    from test_mapper_core import build_map
    build_map(sys.argv[1])
    """
)


def build_map(out_dir: str) -> None:
    """Three keyframes of the synthetic scene -> dense cloud + octree -> map.ply, map.bt."""
    depth, rgb = scene_frame()
    cloud = DenseCloud()
    tree = OccupancyOctree(0.05)
    for i, yaw in enumerate((0.0, 0.05, -0.05)):
        q = np.array([0.0, np.sin(yaw / 2), 0.0, np.cos(yaw / 2)])
        T = pose_to_matrix(np.array([0.02 * i, 0.0, 0.0]), q)
        p, c = keyframe_cloud(depth, rgb, K, SCALE, T)
        cloud.add(i, p, c)
        tree.insert(p, T[:3, 3])
    write_ply(os.path.join(out_dir, "map.ply"), *cloud.cloud())
    tree.write_bt(os.path.join(out_dir, "map.bt"))


def test_outputs_are_byte_identical_across_processes(tmp_path):
    script = _BUILD_SCRIPT.format(tests_dir=str(Path(__file__).resolve().parent))
    outs = []
    for run, seed in enumerate(("0", "12345")):
        d = tmp_path / f"run{run}"
        d.mkdir()
        env = dict(os.environ, PYTHONHASHSEED=seed)
        subprocess.run([sys.executable, "-c", script, str(d)], check=True, env=env, timeout=120)
        outs.append(d)
    d = tmp_path / "inproc"
    d.mkdir()
    build_map(str(d))
    outs.append(d)
    for name in ("map.ply", "map.bt"):
        blobs = [(o / name).read_bytes() for o in outs]
        assert len(blobs[0]) > 1000
        assert blobs[0] == blobs[1] == blobs[2], f"{name} differs between runs"


def test_snapshot_preview_stops_growing_with_the_session():
    """The mapper's Rerun snapshots show a preview of the dense cloud: one point in 8 of each keyframe,
    and at most about PREVIEW_POINTS in all, so a long session's recording grows linearly."""
    from octolog.mapper.process import CLOUD_STRIDE, PREVIEW_POINTS

    rng = np.random.default_rng(0)
    cloud = DenseCloud()
    sizes = []
    for k in range(60):
        cloud.add(k, rng.random((20_000, 3)), rng.integers(0, 255, (20_000, 3), dtype=np.uint8))
        sizes.append(len(cloud.preview(CLOUD_STRIDE, PREVIEW_POINTS)[0]))
    assert sizes[0] == 20_000 // CLOUD_STRIDE and sizes[9] == 10 * 20_000 // CLOUD_STRIDE  # small maps: 1 in 8
    assert max(sizes) <= PREVIEW_POINTS + 60 and sizes[-1] > 0.8 * PREVIEW_POINTS  # then capped, not thinned out
    pts, cols = cloud.preview(CLOUD_STRIDE, PREVIEW_POINTS)
    assert np.array_equal(pts[0], cloud.preview(1)[0][0]) and len(cols) == len(pts)  # each keyframe's first point


def test_a_burst_of_keyframes_past_the_per_second_budget_is_integrated_coarser():
    """mapper.full_keyframes_per_s: within one second of camera time, the keyframes past the budget
    are back-projected at burst_pixel_stride (a quarter of the points at 4), decided by sensor
    stamps alone; a keyframe a second later is at the full stride again."""
    import dataclasses

    from octolog.kit.geometry import RgbdFrame
    from octolog.mapper.config import MapperConfig
    from octolog.mapper.core import make_mapper

    depth, rgb = scene_frame()
    m = make_mapper(dataclasses.replace(MapperConfig(), full_keyframes_per_s=2.0))
    stamps = [0, 100, 200, 300, 1_250]  # ms
    sizes = []
    for i, ms in enumerate(stamps):
        n = m.integrate(i, np.eye(4), RgbdFrame(i, ms * 1_000_000, rgb, depth, SCALE, K))
        sizes.append(n)
    assert [m.keyframes[i].stride for i in range(5)] == [2, 2, 4, 4, 2]
    assert sizes[2] < 0.3 * sizes[0] and sizes[4] == sizes[0]
    unlimited = make_mapper(dataclasses.replace(MapperConfig(), full_keyframes_per_s=0.0))
    unlimited.integrate(0, np.eye(4), RgbdFrame(0, 0, rgb, depth, SCALE, K))
    unlimited.integrate(1, np.eye(4), RgbdFrame(1, 1, rgb, depth, SCALE, K))
    unlimited.integrate(2, np.eye(4), RgbdFrame(2, 2, rgb, depth, SCALE, K))
    assert [kf.stride for kf in unlimited.keyframes.values()] == [2, 2, 2]


def test_a_keyframe_takes_the_trackers_depth_correction_when_it_arrives_and_when_it_changes():
    """The mapper corrects a keyframe's depth by the offset the keyframe carries, and a correction
    (KeyframePoses) with a new offset re-corrects the keyframes it lists: a wall read 1 % short,
    integrated uncorrected, lands where a keyframe integrated with the offset from the start does,
    and the unlisted keyframe keeps its points."""
    beta, z = 0.01 / 3.5, 3.5
    depth, rgb = wall_frame(z / (1 + beta * z))
    frame = RgbdFrame(0, 0, rgb, depth, SCALE, K)
    params = MapperConfig(resolution_m=0.05).params()
    late, first = Mapper(params), Mapper(params)
    late.integrate(0, np.eye(4), frame)
    late.integrate(1, np.eye(4), dataclasses.replace(frame, seq=1, stamp_ns=1))
    first.integrate(0, np.eye(4), dataclasses.replace(frame, depth_inverse_offset=beta))
    assert abs(float(np.median(late.keyframes[0].points_cam[:, 2])) - (z - 0.035)) < 0.002
    assert late.correct({0: np.eye(4)}, depth_inverse_offset=beta) == 1
    assert late.keyframes[0].inverse_offset == beta and late.keyframes[1].inverse_offset == 0.0
    assert abs(float(np.median(late.keyframes[0].points_cam[:, 2])) - z) < 0.002
    assert abs(float(np.median(first.keyframes[0].points_cam[:, 2])) - z) < 0.002
    assert np.median(late.keyframes[1].points_cam[:, 2]) < z - 0.03
    assert late.correct({0: np.eye(4)}, depth_inverse_offset=beta) == 0  # the same offset again: nothing
