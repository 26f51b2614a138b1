"""Keyframe pose graphs with gtsam: the tracker's loop closing, the mapper's joint correction of merged robots.

gtsam is imported where it is used, so a process that never closes a loop does not carry its ~50 MB.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np


def _pose3(T: np.ndarray):
    import gtsam

    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), gtsam.Point3(*T[:3, 3]))


def _matrix(p) -> np.ndarray:
    return np.asarray(p.matrix(), dtype=np.float64)


def optimize_pose_graph(
    poses_wc: np.ndarray,
    edges: list[tuple[int, int, np.ndarray, float]],
    *,
    fixed: int | Iterable[int] = 0,
    iterations: int = 20,
) -> np.ndarray:
    """Keyframe poses that best agree with relative-pose edges (i, j, T_i_j = inv(T_wi) T_wj, weight).

    Edge noise: 1 cm and 0.5 degree divided by sqrt(weight). Keyframe `fixed` (or each of several)
    does not move.
    """
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, T in enumerate(poses_wc):
        values.insert(i, _pose3(T))
    for k in ([fixed] if isinstance(fixed, int) else fixed):
        graph.add(gtsam.NonlinearEqualityPose3(k, _pose3(poses_wc[k])))
    base = np.array([math.radians(0.5)] * 3 + [0.01] * 3)
    for i, j, T_ij, w in edges:
        graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(T_ij),
                                           gtsam.noiseModel.Diagonal.Sigmas(base / math.sqrt(max(w, 1e-6)))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    out = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.stack([_matrix(out.atPose3(i)) for i in range(len(poses_wc))])
