"""2D occupancy grid (mapper.grid): projection, frames, map_server files, nav_msgs round trip.

Hand-made voxel sets only; no ../shared, no rendering.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from octolog.kit.errors import MapError
from octolog.mapper.grid import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    OccupancyGrid2D,
    grid_from_msg,
    map_from_world_for_up,
    occupancy_grid_msg,
    pgm_bytes,
    project_grid,
    project_octree,
    write_map_server,
    yaml_text,
)
from octolog.mapper.octree import OccupancyOctree
from octolog.schemas import codec

RES = 0.1


def centres(ix, iy, iz) -> np.ndarray:
    """Voxel centres (N, 3) for integer index arrays (broadcast), voxel size RES."""
    ix, iy, iz = np.broadcast_arrays(*(np.asarray(a) for a in (ix, iy, iz)))
    return (np.stack([ix.ravel(), iy.ravel(), iz.ravel()], axis=1) + 0.5) * RES


def box_room() -> tuple[np.ndarray, np.ndarray]:
    """A 1.0 x 0.8 m room: walls on voxel columns x 0..9, y 0..7 (ring), heights 0..19 (2 m);
    floor (z index -1) occupied; interior air free; a shelf at z index 15 over cells x 2..3, y 2."""
    occ, free = [], []
    for ix in range(10):
        for iy in range(8):
            wall = ix in (0, 9) or iy in (0, 7)
            occ.append(centres(ix, iy, -1))  # floor below z = 0
            if wall:
                occ.append(centres(ix, iy, np.arange(20)))
            else:
                free.append(centres(ix, iy, np.arange(20)))
    shelf = centres(np.array([2, 3]), 2, 15)
    occ.append(shelf)
    occ_c, free_c = np.concatenate(occ), np.concatenate(free)
    # a shelf voxel is occupied, not free
    keep = ~np.any(np.all(np.isclose(free_c[:, None, :], shelf[None]), axis=2), axis=1)
    return occ_c, free_c[keep]


def test_box_room_grid() -> None:
    occ, free = box_room()
    g = project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=0.1, z_max_m=1.2)
    assert isinstance(g, OccupancyGrid2D)
    assert g.data.dtype == np.int8 and g.data.shape == (8 + 4, 10 + 4)  # 2 padding cells per side
    assert g.origin_xy == pytest.approx((-0.2, -0.2), abs=1e-12)
    room = g.data[2:-2, 2:-2]  # rows = y, columns = x
    walls = np.zeros((8, 10), dtype=bool)
    walls[[0, -1], :] = True
    walls[:, [0, -1]] = True
    assert np.all(room[walls] == OCCUPIED)
    assert np.all(room[~walls] == FREE)  # floor and shelf are outside the band
    pad = np.ones(g.data.shape, dtype=bool)
    pad[2:-2, 2:-2] = False
    assert np.all(g.data[pad] == UNKNOWN)
    assert set(np.unique(g.data).tolist()) == {UNKNOWN, FREE, OCCUPIED}


def test_band_filtering_and_edges() -> None:
    occ, free = box_room()
    # shelf at z index 15 (centre 1.55 m) enters the band; floor (centre -0.05) only with z_min <= -0.05
    g = project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=0.1, z_max_m=1.55)
    assert g.data[2 + 2, 2 + 2] == OCCUPIED and g.data[2 + 2, 2 + 3] == OCCUPIED
    assert g.data[2 + 3, 2 + 2] == FREE
    g2 = project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=-0.05, z_max_m=0.3)
    assert np.all(g2.data[2:-2, 2:-2] == OCCUPIED)  # the floor is in the band: every cell occupied
    g3 = project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=-0.0499, z_max_m=0.3)
    assert g3.data[2 + 3, 2 + 3] == FREE  # just above the floor centre: floor out
    with pytest.raises(MapError, match="no voxels between"):
        project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=5.0, z_max_m=6.0)


def test_cell_semantics() -> None:
    # one column both occupied and free (different heights), one free only, one empty
    occ = centres(0, 0, 3)
    free = np.concatenate([centres(0, 0, 2), centres(1, 0, np.arange(5))])
    g = project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=0.0, z_max_m=1.0,
                     padding_cells=0)
    assert g.data.shape == (1, 2)
    assert g.data.tolist() == [[OCCUPIED, FREE]]
    g = project_grid(occ, centres(3, 2, 0), resolution_m=RES, map_from_world=np.eye(4), z_min_m=0.0,
                     z_max_m=1.0, padding_cells=1)
    assert g.data.shape == (2 + 1 + 2, 4 + 2)
    assert g.data[1, 1] == OCCUPIED and g.data[3, 4] == FREE
    assert (g.data == UNKNOWN).sum() == g.data.size - 2
    # cell_of maps map-frame points to (row, col)
    assert g.cell_of(np.array([[0.05, 0.05], [0.35, 0.25]])).tolist() == [[1, 1], [3, 4]]


def test_free_only_and_occupied_only_inputs() -> None:
    g = project_grid(np.zeros((0, 3)), centres(0, 0, 1), resolution_m=RES, map_from_world=np.eye(4),
                     z_min_m=0.0, z_max_m=1.0, padding_cells=0)
    assert g.data.tolist() == [[FREE]]
    g = project_grid(centres(0, 0, 1), np.zeros((0, 3)), resolution_m=RES, map_from_world=np.eye(4),
                     z_min_m=0.0, z_max_m=1.0, padding_cells=0)
    assert g.data.tolist() == [[OCCUPIED]]


def test_grid_resolution_coarser_than_voxels() -> None:
    occ, free = box_room()
    g = project_grid(occ, free, resolution_m=0.2, map_from_world=np.eye(4), z_min_m=0.1, z_max_m=1.2,
                     padding_cells=0)
    assert g.data.shape == (4, 5)
    assert g.origin_xy == (0.0, 0.0)
    assert np.all(g.data[[0, -1], :] == OCCUPIED) and np.all(g.data[:, [0, -1]] == OCCUPIED)
    assert np.all(g.data[1:-1, 1:-1] == FREE)


def test_origin_is_on_the_resolution_lattice() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-5, 5, size=(200, 3))
    pts[:, 2] = 0.5
    g = project_grid(pts, np.zeros((0, 3)), resolution_m=0.05, map_from_world=np.eye(4), z_min_m=0, z_max_m=1)
    for o in g.origin_xy:
        assert abs(o / 0.05 - round(o / 0.05)) < 1e-9
    rc = g.cell_of(pts[:, :2])
    assert np.all(g.data[rc[:, 0], rc[:, 1]] == OCCUPIED)
    assert (g.data == OCCUPIED).sum() == len(np.unique(rc, axis=0))


def test_rotated_world_gives_the_same_grid() -> None:
    """The tracker's world is an optical frame (y down, z forward): projecting through
    map_from_world_for_up() reproduces the grid of the same voxels given in map coordinates."""
    occ_map, free_map = box_room()
    T = map_from_world_for_up((0.0, -1.0, 0.0), height_m=1.2)  # camera 1.2 m above the floor
    world_from_map = np.linalg.inv(T)

    def to_world(p: np.ndarray) -> np.ndarray:
        return p @ world_from_map[:3, :3].T + world_from_map[:3, 3]

    ref = project_grid(occ_map, free_map, resolution_m=RES, map_from_world=np.eye(4), z_min_m=0.1, z_max_m=1.2)
    g = project_grid(to_world(occ_map), to_world(free_map), resolution_m=RES, map_from_world=T,
                     z_min_m=0.1, z_max_m=1.2)
    np.testing.assert_array_equal(g.data, ref.data)
    assert g.origin_xy == pytest.approx(ref.origin_xy, abs=1e-9)
    np.testing.assert_array_equal(g.map_from_world, T)
    # a point 2 m in front of the camera at floor level is 2 m along map x, at map z = 0
    p = np.array([0.0, 1.2, 2.0, 1.0])  # optical frame: y down
    np.testing.assert_allclose(T @ p, [2.0, 0.0, 0.0, 1.0], atol=1e-12)


def test_project_octree() -> None:
    tree = OccupancyOctree(0.05)
    pts = np.array([[x, 1.0, z] for x in np.arange(-0.5, 0.5, 0.02) for z in np.arange(0.0, 0.6, 0.02)])
    tree.insert(pts, np.array([0.0, -1.0, 0.3]))
    g = project_octree(tree, map_from_world=np.eye(4), z_min_m=0.1, z_max_m=0.5)
    assert g.resolution_m == 0.05
    wall = g.cell_of(np.array([[0.0, 1.0]]))[0]
    cam = g.cell_of(np.array([[0.0, -0.9]]))[0]
    assert g.data[wall[0], wall[1]] == OCCUPIED
    assert g.data[cam[0], cam[1]] == FREE


def test_the_numpy_maps_band_path_gives_the_grid_of_all_centres() -> None:
    """project_octree on our NumPy map in its own frame takes only the band's voxel centres
    (VoxelOccupancyMap.band_centres): the same grid, cell for cell, as projecting every centre."""
    from octolog.mapper.voxelmap import VoxelOccupancyMap

    tree = VoxelOccupancyMap(0.05)
    rng = np.random.default_rng(2)
    for origin in ([0.0, -1.0, 0.3], [0.4, -0.8, 0.9]):
        tree.insert(rng.uniform([-2, 0.5, -0.5], [2, 2.5, 1.5], (4000, 3)), np.array(origin))
    kw = dict(map_from_world=np.eye(4), z_min_m=-0.2, z_max_m=0.35, resolution_m=0.05)
    fast = project_octree(tree, **kw)
    full = project_grid(tree.occupied_centres(), tree.free_centres(), **kw)
    assert np.array_equal(fast.data, full.data) and fast.origin_xy == full.origin_xy
    assert (fast.data == OCCUPIED).any() and (fast.data == FREE).any()


# ---- map_from_world_for_up ----------------------------------------------------------------------


@pytest.mark.parametrize("up", [(0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, -3.0), (1.0, 0.0, 0.0),
                                (0.1, -0.9, 0.2), (1e-5, 2e-5, 1.0), (-0.3, 0.5, 0.8)])
def test_map_from_world_for_up_is_a_proper_frame(up) -> None:
    T = map_from_world_for_up(up)
    R = T[:3, :3]
    u = np.asarray(up) / np.linalg.norm(up)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R @ u, [0.0, 0.0, 1.0], atol=1e-12)  # up maps to +z
    np.testing.assert_allclose(np.cross(R[0], R[1]), R[2], atol=1e-12)  # right-handed
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    fwd = np.array([0.0, 0.0, 1.0]) - u[2] * u  # world z projected on the horizontal plane
    if np.linalg.norm(fwd) > 1e-3:
        np.testing.assert_allclose(R[0], fwd / np.linalg.norm(fwd), atol=1e-12)  # x = forward
    else:
        assert R[0] @ np.array([1.0, 0.0, 0.0]) > 0  # vertical forward: heading from world x
    np.testing.assert_array_equal(map_from_world_for_up(up), T)  # deterministic


def test_map_from_world_for_up_default_and_height() -> None:
    T = map_from_world_for_up()
    np.testing.assert_array_equal(T[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # x fwd, y left, z up
    np.testing.assert_array_equal(map_from_world_for_up((0, 0, 1)), np.eye(4))
    Th = map_from_world_for_up((0.0, -2.0, 0.0), height_m=1.5)
    np.testing.assert_allclose(Th @ [0, 0, 0, 1], [0, 0, 1.5, 1])  # the first camera is 1.5 m up
    np.testing.assert_allclose(Th @ [0, 1.5, 3, 1], [3, 0, 0, 1])  # floor point 3 m ahead
    for bad in [(0, 0, 0), (np.nan, 1, 0), (1, 2)]:
        with pytest.raises(MapError):
            map_from_world_for_up(bad)


# ---- map_server files ---------------------------------------------------------------------------


def small_grid() -> OccupancyGrid2D:
    data = np.array([[OCCUPIED, FREE, FREE],  # row 0 = lowest y
                     [UNKNOWN, FREE, OCCUPIED]], dtype=np.int8)
    return OccupancyGrid2D(data=data, resolution_m=0.05, origin_xy=(-1.25, 2.0), map_from_world=np.eye(4))


def read_pgm(blob: bytes) -> tuple[list[bytes], np.ndarray]:
    lines = blob.split(b"\n", 4)
    assert lines[0] == b"P5"
    w, h = map(int, lines[2].split())
    assert lines[3] == b"255"
    return lines[:4], np.frombuffer(lines[4], dtype=np.uint8).reshape(h, w)


def test_pgm_bytes() -> None:
    blob = pgm_bytes(small_grid())
    assert blob.startswith(b"P5\n# CREATOR: octolog 0.050 m/pix\n3 2\n255\n")
    header, img = read_pgm(blob)
    assert len(blob) == len(b"\n".join(header)) + 1 + 6
    # first image row is the top of the map (highest y): vertical flip
    assert img.tolist() == [[205, 254, 0], [0, 254, 254]]


def test_map_server_trinary_reading_recovers_the_grid() -> None:
    """map_server trinary: p = (255 - v) / 255; p > occupied_thresh -> 100, p < free_thresh -> 0, else -1."""
    occ, free = box_room()
    g = project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=0.1, z_max_m=1.6)
    _, img = read_pgm(pgm_bytes(g))
    cfg = yaml.safe_load(yaml_text(g, "m.pgm"))
    p = (255.0 - img[::-1].astype(np.float64)) / 255.0
    back = np.where(p > cfg["occupied_thresh"], 100, np.where(p < cfg["free_thresh"], 0, -1))
    np.testing.assert_array_equal(back, g.data)


def test_write_map_server(tmp_path) -> None:
    g = small_grid()
    files = write_map_server(g, tmp_path / "floor1")
    assert files == {"pgm": str(tmp_path / "floor1.pgm"), "yaml": str(tmp_path / "floor1.yaml")}
    assert (tmp_path / "floor1.pgm").read_bytes() == pgm_bytes(g)
    text = (tmp_path / "floor1.yaml").read_text()
    cfg = yaml.safe_load(text)
    assert cfg == {"image": "floor1.pgm", "mode": "trinary", "resolution": 0.05, "origin": [-1.25, 2.0, 0.0],
                   "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196}
    assert text.splitlines()[0] == "image: floor1.pgm"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["floor1.pgm", "floor1.yaml"]  # no temp files left
    # OpenCV reads it as the same 8-bit image
    import cv2

    img = cv2.imread(str(tmp_path / "floor1.pgm"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.tolist() == [[205, 254, 0], [0, 254, 254]]
    with pytest.raises(MapError, match="cannot write"):
        write_map_server(g, tmp_path / "missing-dir" / "m")


def test_map_server_bytes_are_deterministic(tmp_path) -> None:
    occ, free = box_room()
    rng = np.random.default_rng(0)
    a = project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=0.1, z_max_m=1.2)
    b = project_grid(occ[rng.permutation(len(occ))], free[rng.permutation(len(free))], resolution_m=RES,
                     map_from_world=np.eye(4), z_min_m=0.1, z_max_m=1.2)
    np.testing.assert_array_equal(a.data, b.data)
    assert a.origin_xy == b.origin_xy
    write_map_server(a, tmp_path / "a")
    write_map_server(b, tmp_path / "b")
    assert (tmp_path / "a.pgm").read_bytes() == (tmp_path / "b.pgm").read_bytes()
    assert (tmp_path / "a.yaml").read_text().replace("a.pgm", "b.pgm") == (tmp_path / "b.yaml").read_text()


def test_writer_rejects_bad_grids() -> None:
    g = OccupancyGrid2D(np.zeros((0, 3), np.int8), 0.05, (0.0, 0.0), np.eye(4))
    with pytest.raises(MapError):
        pgm_bytes(g)
    g = OccupancyGrid2D(np.full((2, 2), 101, np.int16), 0.05, (0.0, 0.0), np.eye(4))
    with pytest.raises(MapError):
        pgm_bytes(g)


# ---- nav_msgs/OccupancyGrid ---------------------------------------------------------------------


def test_occupancy_grid_msg_round_trip() -> None:
    g = small_grid()
    T = map_from_world_for_up()
    g = OccupancyGrid2D(g.data, g.resolution_m, g.origin_xy, T)
    stamp = 1_700_000_123_456_789_012
    msg = occupancy_grid_msg(g, stamp)
    assert msg.header.frame_id == "map"
    assert codec.stamp_ns(msg.header) == stamp
    assert (msg.info.width, msg.info.height) == (3, 2)
    assert (msg.info.map_load_time.sec, msg.info.map_load_time.nanosec) == (stamp // 10**9, stamp % 10**9)
    o = msg.info.origin
    assert (o.position.x, o.position.y, o.position.z) == (-1.25, 2.0, 0.0)
    assert (o.orientation.x, o.orientation.y, o.orientation.z, o.orientation.w) == (0.0, 0.0, 0.0, 1.0)
    # row-major from the lower-left cell: data[x + y * width] == grid.data[y, x]
    assert msg.data.dtype == np.int8
    assert msg.data.tolist() == [100, 0, 0, -1, 0, 100]
    wire = codec.encode(msg, "nav_msgs/msg/OccupancyGrid")
    back = grid_from_msg(codec.decode(wire, "nav_msgs/msg/OccupancyGrid"), T)
    np.testing.assert_array_equal(back.data, g.data)
    assert back.data.dtype == np.int8
    assert back.resolution_m == 0.05  # float32 on the wire, read back as the short decimal
    assert back.origin_xy == g.origin_xy
    np.testing.assert_array_equal(back.map_from_world, T)
    np.testing.assert_array_equal(grid_from_msg(msg).map_from_world, np.eye(4))
    assert occupancy_grid_msg(g, stamp, frame_id="odom").header.frame_id == "odom"


def test_grid_from_msg_rejects_inconsistent_messages() -> None:
    msg = occupancy_grid_msg(small_grid(), 0)
    msg.data = msg.data[:-1]
    with pytest.raises(MapError, match="expected 3x2"):
        grid_from_msg(msg)
    msg = occupancy_grid_msg(small_grid(), 0)
    q = msg.info.origin.orientation
    q.z, q.w = math.sin(0.25), math.cos(0.25)
    with pytest.raises(MapError, match="rotated"):
        grid_from_msg(msg)


def test_projection_rejects_bad_input() -> None:
    occ, free = box_room()
    kw = dict(map_from_world=np.eye(4), z_min_m=0.0, z_max_m=1.0)
    with pytest.raises(MapError):
        project_grid(occ, free, resolution_m=0.0, **kw)
    with pytest.raises(MapError):
        project_grid(occ[:, :2], free, resolution_m=RES, **kw)
    with pytest.raises(MapError):
        project_grid(occ, free, resolution_m=RES, map_from_world=np.eye(4), z_min_m=1.0, z_max_m=0.0)
    with pytest.raises(MapError):
        project_grid(occ, free, resolution_m=RES, map_from_world=2 * np.eye(4), z_min_m=0.0, z_max_m=1.0)
    with pytest.raises(MapError):
        project_grid(occ, free, resolution_m=RES, padding_cells=-1, **kw)
