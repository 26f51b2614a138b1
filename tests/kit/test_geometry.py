"""kit/geometry.py's rotation conversions: scipy's arithmetic, bit for bit, without scipy.spatial in
the stage processes (every output's bytes depend on them: trajectory.txt, the messages' quaternions,
the synthetic room's path)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from scipy.spatial.transform import Rotation

from octolog.kit.geometry import euler_to_matrices, matrices_to_quats, matrix_to_pose, pose_to_matrix, quats_to_matrices


def test_conversions_give_scipys_bits() -> None:
    rng = np.random.default_rng(7)
    q = rng.normal(size=(3000, 4))
    R = Rotation.from_quat(q).as_matrix()
    assert np.array_equal(quats_to_matrices(q), R)
    # nearly orthogonal (a solver's output) and clearly not (replaced by the nearest rotation)
    off = R + rng.normal(size=R.shape) * np.where(rng.random(len(R)) < 0.3, 1e-6, 1e-15)[:, None, None]
    assert np.array_equal(matrices_to_quats(off), Rotation.from_matrix(off).as_quat())
    half_turns = np.stack([np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])])
    assert np.array_equal(matrices_to_quats(half_turns), Rotation.from_matrix(half_turns).as_quat())
    angles = rng.uniform(-3.0, 3.0, (3000, 3))
    assert np.array_equal(euler_to_matrices("ZYX", angles), Rotation.from_euler("ZYX", angles).as_matrix())


def test_a_pose_goes_to_a_quaternion_with_w_up_and_back() -> None:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 3.0]).as_matrix()
    T[:3, 3] = [1.0, 2.0, 3.0]
    t, q = matrix_to_pose(T)
    assert q[3] >= 0 and np.allclose(pose_to_matrix(t, q), T, atol=1e-15)


def test_no_stage_imports_scipy_spatial() -> None:
    """0.4 s of CPU at every stage's start (a test run starts hundreds): the tracker, the mapper and
    the replay do without it, after their warm-up conversions."""
    code = ("import sys, numpy as np\n"
            "import octolog.tracker.node, octolog.mapper.node, octolog.replay.node, octolog.shell.run\n"
            "from octolog.kit.geometry import matrix_to_pose; matrix_to_pose(np.eye(4))\n"
            "from octolog.replay.sources import open_source; open_source('synthetic:3').gravity_up()\n"
            "print('scipy.spatial' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
