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


def pose_to_matrix(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from translation and quaternion (x, y, z, w)."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs 0.5 s and ~40 MB to import

    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()
    T[:3, 3] = t_xyz
    return T


def matrix_to_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation and quaternion (x, y, z, w, with w >= 0) of a 4x4 transform."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T[:3, :3]).as_quat()
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
