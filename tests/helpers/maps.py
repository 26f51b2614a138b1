"""Comparing maps and map frames: voxel agreement of two OctoMap files, angles between directions."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from octolog.kit import metrics


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Degrees between directions `a` and `b`."""
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0)))


def z_tilt(session: Path, map_from_world: np.ndarray) -> float:
    """Degrees between the ground truth's z (up) and the session's map-frame z, through the SE(3)
    alignment (Umeyama on positions, as ATE uses) of the map-frame trajectory onto the ground truth."""
    est, gt = metrics.read_tum(session / "trajectory.txt"), metrics.read_tum(session / "groundtruth.txt")
    R, t = map_from_world[:3, :3], map_from_world[:3, 3]
    rot = R @ Rotation.from_quat(est.quats_xyzw).as_matrix()
    in_map = metrics.Trajectory(est.stamps_ns, est.positions @ R.T + t, Rotation.from_matrix(rot).as_quat())
    return math.degrees(math.acos(np.clip(metrics.ate(in_map, gt).alignment[2, 2], -1.0, 1.0)))


def cells(path: Path) -> dict[tuple[int, int, int], bool]:
    """Every known 5 cm voxel of a .bt file (merged leaves expanded): occupied or not."""
    import octomap

    tree = octomap.OcTree(0.05)
    assert tree.readBinary(str(path).encode())
    known = {}
    for it in tree.begin_leafs():
        occupied = bool(tree.isNodeOccupied(it))
        k = round(it.getSize() / 0.05)
        low = np.floor((np.array(it.getCoordinate()) - it.getSize() / 2) / 0.05 + 0.5).astype(int)
        for i in range(k):
            for j in range(k):
                for m in range(k):
                    known[(low[0] + i, low[1] + j, low[2] + m)] = occupied
    return known


def occupied_disagreement(a: Path | dict, b: Path | dict, tolerance: int = 0) -> tuple[float, int]:
    """Of the voxels both maps know and at least one calls occupied, the share they disagree on
    (occupied in one, free in the other); and how many such voxels there are. With `tolerance` t, a
    voxel occupied in one map is not counted when the other has an occupied voxel within t voxels
    (the 3D neighbourhood): a surface one voxel over agrees."""
    ca, cb = (cells(m) if isinstance(m, Path) else m for m in (a, b))
    both = [c for c in ca.keys() & cb.keys() if ca[c] or cb[c]]
    occupied = ({c for c, v in ca.items() if v}, {c for c, v in cb.items() if v})
    near = list(itertools.product(range(-tolerance, tolerance + 1), repeat=3))

    def missing(c: tuple[int, int, int], occ: set) -> bool:
        return not any((c[0] + i, c[1] + j, c[2] + k) in occ for i, j, k in near)

    wrong = sum((ca[c] and missing(c, occupied[1])) or (cb[c] and missing(c, occupied[0])) for c in both)
    return wrong / max(len(both), 1), len(both)
