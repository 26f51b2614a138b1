"""Own occupancy map (mapper.voxelmap) against OctoMap (pyoctomap / octomap-python).

Synthetic scenes are built here; the TUM check runs when OCTOLOG_DATA points at the shared data.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from octolog.kit.errors import MapError
from octolog.kit.geometry import Intrinsics, pose_to_matrix
from octolog.mapper.cloud import backproject, keyframe_cloud, transform
from octolog.mapper.occupancy import make_occupancy_map
from octolog.mapper.octree import OccupancyOctree
from octolog.mapper.sensor_model import SensorModel
from octolog.mapper.voxelmap import VoxelOccupancyMap

K = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
SCALE = 0.001
RES = 0.05


def scene(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Wall at 2.5 m, a box at 1.2 m, a slanted floor, holes, noise and flying pixels."""
    rng = np.random.default_rng(seed)
    h, w = 480, 640
    depth = np.full((h, w), 2500, dtype=np.int32)
    depth[150:330, 220:420] = 1200
    rows = np.arange(h)[:, None]
    depth = np.where(rows > 380, np.minimum(depth, 1000 + (480 - rows) * 15), depth)
    depth = depth + rng.integers(-3, 4, depth.shape)
    depth[rng.random(depth.shape) < 0.02] = 0
    fly = rng.random(depth.shape) < 0.002
    depth[fly] = rng.integers(1300, 2400, int(fly.sum()))
    rgb = np.zeros((h, w, 3), dtype=np.uint8)
    rgb[..., 0] = (np.arange(w) * 255 // (w - 1))[None, :]
    rgb[..., 1] = (np.arange(h) * 255 // (h - 1))[:, None]
    rgb[..., 2] = rng.integers(0, 256, (h, w))
    return depth.astype(np.uint16), rgb


def poses(n: int = 4) -> list[np.ndarray]:
    out = []
    for i in range(n):
        yaw, pitch = 0.07 * i - 0.1, 0.03 * i
        q = np.array([np.sin(pitch / 2), np.sin(yaw / 2), 0.0, np.cos(yaw / 2)])
        out.append(pose_to_matrix(np.array([0.013 + 0.031 * i, -0.021 * i, 0.017 * i]), q / np.linalg.norm(q)))
    return out


def voxel_state(centres_occ: np.ndarray, centres_free: np.ndarray) -> dict[tuple[int, int, int], int]:
    out: dict[tuple[int, int, int], int] = {}
    for c, s in ((centres_free, 0), (centres_occ, 1)):
        for k in np.floor(c / RES).astype(np.int64):
            out[tuple(k)] = s
    return out


def agreement(a, b) -> float:
    """Share of voxels known to either map whose state (occupied/free/unknown) agrees."""
    sa = voxel_state(a.occupied_centres(), a.free_centres())
    sb = voxel_state(b.occupied_centres(), b.free_centres())
    union = set(sa) | set(sb)
    same = sum(1 for k in union if sa.get(k, -1) == sb.get(k, -1))
    return same / max(1, len(union))


def both(clouds, *, max_range: float = -1.0, colour: bool = False):
    ref = OccupancyOctree(RES, colour=colour)
    own = VoxelOccupancyMap(RES)
    for pts, cols, T in clouds:
        ref.insert(pts, T[:3, 3], colours=cols if colour else None, max_range_m=max_range)
        own.insert(pts, T[:3, 3], colours=cols, max_range_m=max_range)
    return ref, own


def raw_clouds(stride: int = 2, n: int = 4):
    depth, rgb = scene()
    out = []
    for T in poses(n):
        p, c = backproject(depth, rgb, K, SCALE, stride=stride)
        out.append((transform(p, T), c, T))
    return out


# ---- agreement with OctoMap ----------------------------------------------------------------------


@pytest.mark.parametrize("max_range", [-1.0, 2.2])
def test_same_tree_as_octomap_on_raw_clouds(max_range):
    ref, own = both(raw_clouds(stride=2), max_range=max_range)
    assert own.stats()["occupied_voxels"] > 1000 and own.stats()["free_voxels"] > 10000
    assert agreement(ref, own) == 1.0
    # The full log-odds tree (in-memory pruning included) and the .bt are byte for byte OctoMap's.
    assert own.ot_bytes(colour=False) == ref.ot_bytes()
    assert own.bt_bytes() == ref.bt_bytes()


def test_compiled_and_vectorised_ray_walks_give_the_same_tree(monkeypatch):
    """The compiled walk (mapper/kernels.py, dense scan grids) and the vectorised one (kept for scan
    boxes too large for a dense grid) mark the same voxels: forced onto the vectorised path, the
    same scans give the same .ot bytes, and both are OctoMap's."""
    from octolog.mapper import voxelmap

    clouds = raw_clouds(stride=3)
    ref, compiled = both(clouds, max_range=2.2)
    monkeypatch.setattr(voxelmap, "_DENSE_MAX_CELLS", 0)
    vectorised = VoxelOccupancyMap(RES)
    for pts, _, T in clouds:
        vectorised.insert(pts, T[:3, 3], max_range_m=2.2)
    assert compiled.ot_bytes(colour=False) == vectorised.ot_bytes(colour=False) == ref.ot_bytes()


def test_insert_all_is_one_insert_after_another():
    """A rebuild's `insert_all` (the next scan's rays cast on a second thread) gives the bytes of
    one `insert` after another, colours, clamping and a cut range included; a bad scan raises what
    `insert` raises, after the scans before it went in."""
    clouds = raw_clouds(stride=4, n=3) * 3
    one_by_one, all_at_once = VoxelOccupancyMap(RES), VoxelOccupancyMap(RES)
    for pts, cols, T in clouds:
        one_by_one.insert(pts, T[:3, 3], colours=cols, max_range_m=2.2)
    all_at_once.insert_all(((pts, T[:3, 3], cols) for pts, cols, T in clouds), max_range_m=2.2)
    assert all_at_once.ot_bytes() == one_by_one.ot_bytes() and all_at_once.bt_bytes() == one_by_one.bt_bytes()
    partial, first = VoxelOccupancyMap(RES), VoxelOccupancyMap(RES)
    (pts, cols, T), bad = clouds[0], np.full((5, 3), np.nan)
    first.insert(pts, T[:3, 3], colours=cols)
    with pytest.raises(MapError, match="NaN"):
        partial.insert_all([(pts, T[:3, 3], cols), (bad, T[:3, 3], None), (pts, T[:3, 3], cols)])
    assert partial.ot_bytes() == first.ot_bytes()


def test_a_checkpoint_restored_goes_on_as_if_it_had_never_left():
    """`checkpoint` then `restore` (twice: the checkpoint stays as it was): the scans inserted after a
    restore give the bytes of a map that took them straight after the checkpointed ones, confirmation
    window and masked end points included."""
    clouds = raw_clouds(stride=4, n=3)
    (a, ca, Ta), (b, cb, Tb), (c, cc, Tc) = clouds
    m = VoxelOccupancyMap(RES, confirm_within=2)
    m.insert(a, Ta[:3, 3], colours=ca)
    m.insert(b, Tb[:3, 3], colours=cb)
    cp = m.checkpoint()
    m.insert(c, Tc[:3, 3], colours=cc)
    straight = VoxelOccupancyMap(RES, confirm_within=2)
    for pts, cols, T in ((a, ca, Ta), (b, cb, Tb), (a, ca, Tc)):
        straight.insert(pts, T[:3, 3], colours=cols)
    for _ in range(2):
        m.restore(cp)
        m.insert(a, Tc[:3, 3], colours=ca)  # another scan than the one the checkpoint was followed by
        assert m.ot_bytes() == straight.ot_bytes() and m.masked_total == straight.masked_total
        assert np.array_equal(m.masked, straight.masked)


def test_same_tree_as_octomap_on_filtered_clouds():
    depth, rgb = scene()
    clouds = []
    for T in poses(5):
        p, c = keyframe_cloud(depth, rgb, K, SCALE, T, max_range_m=4.0)
        clouds.append((p, c, T))
    ref, own = both(clouds, max_range=4.0)
    assert agreement(ref, own) == 1.0
    assert own.ot_bytes(colour=False) == ref.ot_bytes()
    assert own.bt_bytes() == ref.bt_bytes()


def test_clamping_and_repeated_scans_match():
    clouds = raw_clouds(stride=4, n=2) * 6  # 12 scans: log-odds reach both clamping bounds
    ref, own = both(clouds)
    lo = own.logodds_values()
    assert lo.max() == pytest.approx(np.log(0.97 / 0.03), rel=1e-6)
    assert lo.min() == pytest.approx(np.log(0.12 / 0.88), rel=1e-6)
    assert own.ot_bytes(colour=False) == ref.ot_bytes()
    assert own.bt_bytes() == ref.bt_bytes()


def test_undiscretized_rays_match_octomap_default():
    import pyoctomap

    pts, _, T = raw_clouds(stride=8, n=1)[0]
    ref = OccupancyOctree(RES)
    ref.tree.insertPointCloud(np.ascontiguousarray(pts), T[:3, 3].copy(), max_range=2.0,
                              lazy_eval=False, discretize=False)
    own = VoxelOccupancyMap(RES)
    own.insert(pts, T[:3, 3], max_range_m=2.0, discretize=False)
    assert isinstance(ref.tree, pyoctomap.OcTree)
    assert own.ot_bytes(colour=False) == ref.ot_bytes()


def test_colour_tree_agrees_with_octomap_colour_backend(tmp_path):
    """Same leaf states; colours equal except where OctoMap's ColorOcTree pruned (lossy) in memory."""
    import pyoctomap

    ref, own = both(raw_clouds(stride=2, n=3), max_range=3.0, colour=True)
    own.write_ot(tmp_path / "own.ot")
    ref.write_ot(tmp_path / "ref.ot")
    head = (tmp_path / "own.ot").read_bytes()[:200]
    assert head.startswith(b"# Octomap OcTree file\n") and b"\nid ColorOcTree\n" in head
    s_own, c_own = _leaf_voxels(pyoctomap.ColorOcTree(str(tmp_path / "own.ot")), RES, with_colour=True)
    s_ref, c_ref = _leaf_voxels(pyoctomap.ColorOcTree(str(tmp_path / "ref.ot")), RES, with_colour=True)
    assert s_own == s_ref
    occ = [k for k, s in s_own.items() if s]
    same = sum(1 for k in occ if c_own[k] == c_ref[k]) / len(occ)
    print(f"colour agreement with the ColorOcTree backend: {100 * same:.2f}% of {len(occ)} occupied voxels")
    assert same >= 0.9


# ---- files read by OctoMap -----------------------------------------------------------------------


def _leaf_voxels(tree, resolution: float, with_colour: bool = False):
    """Expand an OctoMap tree's leaves to full-resolution voxel keys -> state (and colour)."""
    state: dict[tuple[int, int, int], int] = {}
    colour: dict[tuple[int, int, int], tuple[int, int, int]] = {}
    for it in tree.begin_leafs():
        w = int(round(it.getSize() / resolution))
        first = np.rint(np.asarray(it.getCoordinate(), float) / resolution - w / 2.0).astype(np.int64)
        occ = 1 if tree.isNodeOccupied(it) else 0
        rgb = None
        if with_colour:
            node = tree.search(np.asarray(it.getCoordinate(), dtype=np.float64))
            rgb = tuple(int(v) for v in node.getColor())
        g = np.arange(w)
        for off in np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3):
            k = tuple(int(v) for v in first + off)
            state[k] = occ
            if with_colour:
                colour[k] = rgb
    return state, colour


def _own_voxels(own: VoxelOccupancyMap):
    keys = own.keys() - 32768
    occ = own.occupied_mask()
    state = {tuple(int(v) for v in k): int(o) for k, o in zip(keys, occ)}
    colour = {tuple(int(v) for v in k): tuple(int(x) for x in c) for k, c in zip(keys, own.colours())}
    return state, colour


def test_bt_read_by_octomap_python_has_identical_leaf_states(tmp_path):
    octomap = pytest.importorskip("octomap")
    _, own = both(raw_clouds(stride=4, n=3), max_range=3.0)
    own.write_bt(tmp_path / "own.bt")
    t = octomap.OcTree(RES)
    assert t.readBinary(str(tmp_path / "own.bt").encode())
    theirs, _ = _leaf_voxels(t, RES)
    mine, _ = _own_voxels(own)
    assert theirs == mine


def test_ot_read_by_pyoctomap_has_identical_leaf_states_and_colours(tmp_path):
    import pyoctomap

    own = VoxelOccupancyMap(RES)
    for pts, cols, T in raw_clouds(stride=4, n=3):
        own.insert(pts, T[:3, 3], colours=cols, max_range_m=3.0)
    # Force a coloured pruning case: 8 sibling voxels with equal log-odds and equal colour.
    block = (np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * RES
    block = block + np.array([2.0, 2.0, 0.0])
    own.insert(block, np.array([2.0, 2.0, 2.0]), colours=np.full((8, 3), 40, np.uint8))
    path = tmp_path / "own.ot"
    own.write_ot(path)
    t = pyoctomap.ColorOcTree(str(path))
    assert t.getTreeType() == "ColorOcTree"
    theirs, their_col = _leaf_voxels(t, RES, with_colour=True)
    mine, my_col = _own_voxels(own)
    assert theirs == mine
    assert their_col == my_col
    assert sum(1 for s in mine.values() if s) > 500


def test_empty_map_files_are_valid(tmp_path):
    octomap = pytest.importorskip("octomap")
    m = VoxelOccupancyMap()
    m.write_bt(tmp_path / "e.bt")
    assert m.bt_bytes() == OccupancyOctree().bt_bytes()
    assert m.ot_bytes(colour=False) == OccupancyOctree().ot_bytes()
    t = octomap.OcTree(RES)
    assert t.readBinary(str(tmp_path / "e.bt").encode()) and t.size() == 0
    assert m.occupied_centres().shape == (0, 3) and m.stats()["known_volume_m3"] == 0.0


# ---- determinism ---------------------------------------------------------------------------------

_SCRIPT = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    from test_voxelmap import build_files
    build_files(sys.argv[1])
    """
)


def build_files(out_dir: str) -> None:
    m = VoxelOccupancyMap(RES)
    for pts, cols, T in raw_clouds(stride=4, n=3):
        m.insert(pts, T[:3, 3], colours=cols, max_range_m=3.0)
    m.write_bt(os.path.join(out_dir, "m.bt"))
    m.write_ot(os.path.join(out_dir, "m.ot"))


def test_files_are_byte_identical_across_processes(tmp_path):
    script = _SCRIPT.format(tests=str(Path(__file__).resolve().parent))
    dirs = []
    for i, seed in enumerate(("0", "4242")):
        d = tmp_path / f"run{i}"
        d.mkdir()
        subprocess.run([sys.executable, "-c", script, str(d)], check=True, timeout=300,
                       env=dict(os.environ, PYTHONHASHSEED=seed))
        dirs.append(d)
    for name in ("m.bt", "m.ot"):
        blobs = [(d / name).read_bytes() for d in dirs]
        assert len(blobs[0]) > 1000 and blobs[0] == blobs[1]


# ---- API -----------------------------------------------------------------------------------------


def test_factory_and_common_interface(tmp_path):
    pts, cols, T = raw_clouds(stride=8, n=1)[0]
    maps = [make_occupancy_map(b, RES) for b in ("numpy", "octomap")]
    for m in maps:
        assert m.insert(pts, T[:3, 3], colours=cols, max_range_m=3.0) == pts.shape[0]
        m.write_bt(tmp_path / f"{m.backend}.bt")
        m.write_ot(tmp_path / f"{m.backend}.ot")
    a, b = maps
    assert np.array_equal(a.occupied_centres(), b.occupied_centres())
    assert np.array_equal(a.free_centres(), b.free_centres())
    sa, sb = a.stats(), b.stats()
    for key in ("occupied_voxels", "free_voxels", "known_volume_m3"):
        assert sa[key] == sb[key]
    assert (tmp_path / "numpy.bt").read_bytes() == (tmp_path / "octomap.bt").read_bytes()
    probe = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, -3.0]]) + T[:3, 3]
    assert a.classify(probe).tolist() == b.classify(probe).tolist()
    a.clear()
    assert a.stats()["known_volume_m3"] == 0.0
    with pytest.raises(MapError):
        make_occupancy_map("voxblox")


def test_rejects_bad_inputs(tmp_path):
    m = VoxelOccupancyMap()
    with pytest.raises(MapError):
        m.insert(np.zeros((4, 2)), np.zeros(3))
    with pytest.raises(MapError):
        m.insert(np.zeros((4, 3)), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(MapError):
        m.insert(np.full((4, 3), np.nan), np.zeros(3))
    with pytest.raises(MapError):
        m.insert(np.full((4, 3), 5000.0), np.zeros(3))
    with pytest.raises(MapError):
        m.insert(np.ones((4, 3)), np.zeros(3), colours=np.zeros((4, 3), np.float32))
    with pytest.raises(MapError):
        m.insert(np.ones((4, 3)), np.zeros(3), max_range_m=0.0)
    with pytest.raises(MapError):
        VoxelOccupancyMap(0.0)
    with pytest.raises(MapError):
        VoxelOccupancyMap(model=SensorModel(prob_hit=0.3))
    with pytest.raises(MapError, match="cannot write"):
        m.write_bt(tmp_path / "missing" / "x.bt")
    assert m.insert(np.zeros((0, 3)), np.zeros(3)) == 0


# ---- TUM fr1/xyz with ground-truth poses ---------------------------------------------------------


def tum_keyframes(data: Path, n: int = 10, every: int = 10):
    """(frame, world_from_camera) for n frames `every` apart with a GT pose within 20 ms."""
    from octolog.kit.metrics import associate, read_tum
    from octolog.kit.tum import open_tum

    seq = open_tum(data / "tum" / "rgbd_dataset_freiburg1_xyz_first300")
    gt = read_tum(seq.groundtruth)
    frames = [f for i, f in enumerate(seq.frames(0, n * every)) if i % every == 0]
    ia, ib = associate(np.array([f.stamp_ns for f in frames]), gt.stamps_ns, 20_000_000)
    mats = gt.matrices()
    return [(frames[i], mats[j]) for i, j in zip(ia, ib)]


@pytest.mark.skipif(not os.environ.get("OCTOLOG_DATA"), reason="OCTOLOG_DATA not set")
@pytest.mark.parametrize("cloud", ["raw", "filtered"])
def test_tum_agreement_with_octomap(cloud, tmp_path):
    kfs = tum_keyframes(Path(os.environ["OCTOLOG_DATA"]))
    assert len(kfs) >= 8
    clouds = []
    for f, T in kfs:
        if cloud == "raw":
            p, c = backproject(f.depth, f.rgb, f.intrinsics, f.depth_scale_m, max_range_m=4.0, stride=1)
            p = transform(p, T)
        else:
            p, c = keyframe_cloud(f.depth, f.rgb, f.intrinsics, f.depth_scale_m, T, max_range_m=4.0)
        clouds.append((p, c, T))
    ref, own = both(clouds, max_range=4.0)
    share = agreement(ref, own)
    print(f"TUM {cloud}: state agreement {100 * share:.4f}% over {len(voxel_state(own.occupied_centres(), own.free_centres()))} voxels")
    assert share >= 0.99
    assert own.ot_bytes(colour=False) == ref.ot_bytes()
    assert own.bt_bytes() == ref.bt_bytes()
