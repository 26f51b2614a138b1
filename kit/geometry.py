"""Plain data types shared by every stage: camera model, RGB-D frame, pose helpers.

No transport, no I/O: stage cores import this module only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera model (plumb-bob distortion k1 k2 p1 p2 k3, may be empty)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RgbdFrame:
    """A colour image with its registered depth image.

    `depth` keeps the sensor's integer units; metres = depth * depth_scale_m (0 = no reading).
    """

    seq: int
    stamp_ns: int
    rgb: np.ndarray  # (H, W, 3) uint8, RGB order
    depth: np.ndarray  # (H, W) uint16
    depth_scale_m: float
    intrinsics: Intrinsics
    frame_id: str = "camera_color_optical_frame"
    extra: dict = field(default_factory=dict, compare=False)
    # the depth camera's bias correction this frame's depth takes (1/m): 1/z <- 1/z - offset. A
    # keyframe carries the tracker's (Keyframe.depth_inverse_offset); `depth` stays raw.
    depth_inverse_offset: float = 0.0

    def depth_m(self) -> np.ndarray:
        return self.depth.astype(np.float32) * np.float32(self.depth_scale_m)


@dataclass(frozen=True)
class EncodedRgbd:
    """An RGB-D frame whose images are still encoded as the source stores them: PNG/JPEG files or
    CompressedImage payloads, with their image_transport format strings ("rgb8; png compressed
    bgr8", "16UC1; png compressed"). Published and logged as they are, decoded where pixels are
    needed (the tracker), so nothing decodes and re-encodes on the way."""

    seq: int
    stamp_ns: int
    color: bytes
    color_format: str
    depth: bytes
    depth_format: str
    depth_scale_m: float
    intrinsics: Intrinsics
    frame_id: str = "camera_color_optical_frame"


def quats_to_matrices(quats_xyzw: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of (N, 4) quaternions (x, y, z, w; normalised first). The arithmetic of
    scipy's `Rotation.from_quat(q).as_matrix()`, bit for bit, without importing scipy.spatial
    (0.4 s of CPU in every process that would)."""
    q = np.asarray(quats_xyzw, dtype=float).reshape(-1, 4)
    q = q / np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])[:, None]
    return _unit_quats_to_matrices(q)


def _unit_quats_to_matrices(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.stack([np.stack([x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)], axis=-1),
                     np.stack([2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)], axis=-1),
                     np.stack([2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2], axis=-1)], axis=1)


def matrices_to_quats(rotations: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) of (N, 3, 3) rotations, as scipy's
    `Rotation.from_matrix(R).as_quat()` computes them, bit for bit: a matrix further than 1e-12 from
    orthogonal is first replaced by its nearest rotation (SVD), then Shepperd's method from the
    largest of the diagonal and the trace."""
    R = np.array(rotations, dtype=float).reshape(-1, 3, 3)
    gram = R @ np.swapaxes(R, 1, 2)
    off = ~np.all(np.isclose(gram, np.eye(3), atol=1e-12), axis=(1, 2))
    if off.any():
        u, _, vt = np.linalg.svd(R[off], full_matrices=False)
        R[off] = u @ vt
    trace = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    choice = np.argmax(np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], trace], axis=1), axis=1)
    q = np.empty((len(R), 4))
    for i in range(3):
        rows = choice == i
        j, k = (i + 1) % 3, (i + 2) % 3
        m = R[rows]
        q[rows, i] = 1 - trace[rows] + 2 * m[:, i, i]
        q[rows, j] = m[:, j, i] + m[:, i, j]
        q[rows, k] = m[:, k, i] + m[:, i, k]
        q[rows, 3] = m[:, k, j] - m[:, j, k]
    rows = choice == 3
    m = R[rows]
    q[rows, 0] = m[:, 2, 1] - m[:, 1, 2]
    q[rows, 1] = m[:, 0, 2] - m[:, 2, 0]
    q[rows, 2] = m[:, 1, 0] - m[:, 0, 1]
    q[rows, 3] = 1 + trace[rows]
    return q / np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])[:, None]


def euler_to_matrices(axes: str, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of intrinsic Euler angles (N, len(axes)) about `axes` (uppercase, as
    scipy's `Rotation.from_euler("ZYX", angles).as_matrix()`, bit for bit): the elementary
    quaternions composed in order."""
    angles = np.asarray(angles, dtype=float).reshape(-1, len(axes))
    q = None
    for n, axis in enumerate(axes):
        e = np.zeros((len(angles), 4))
        e[:, 3] = np.cos(angles[:, n] / 2.0)
        e[:, "XYZ".index(axis)] = np.sin(angles[:, n] / 2.0)
        q = e if q is None else _compose_quats(q, e)
    return _unit_quats_to_matrices(q)


def _compose_quats(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """p * q (Hamilton product) of (N, 4) quaternions (x, y, z, w)."""
    c0 = p[:, 1] * q[:, 2] - p[:, 2] * q[:, 1]
    c1 = p[:, 2] * q[:, 0] - p[:, 0] * q[:, 2]
    c2 = p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]
    return np.stack([p[:, 3] * q[:, 0] + q[:, 3] * p[:, 0] + c0,
                     p[:, 3] * q[:, 1] + q[:, 3] * p[:, 1] + c1,
                     p[:, 3] * q[:, 2] + q[:, 3] * p[:, 2] + c2,
                     p[:, 3] * q[:, 3] - (p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1] + p[:, 2] * q[:, 2])], axis=1)


def pose_to_matrix(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from translation and quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = quats_to_matrices(q_xyzw)[0]
    T[:3, 3] = t_xyz
    return T


def matrix_to_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation and quaternion (x, y, z, w, with w >= 0) of a 4x4 transform."""
    q = matrices_to_quats(T[:3, :3])[0]
    if q[3] < 0:
        q = -q
    return T[:3, 3].copy(), q


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti
