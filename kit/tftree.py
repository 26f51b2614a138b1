"""The static part of the TF tree as it arrives on `/tf_static`, for a stage that must attach its
own transform at the right frame.

REP 105 wants one parent per frame: `map` -> `world` -> `camera_link` -> ... -> the colour camera's
optical frame. The camera's own tree (`camera_link` -> optical frames, the IMU) comes from whoever
knows the camera (the recorder, or the replay for a file); the tracker then publishes the moving
part, `world` -> the camera tree's root, composed from its pose of the optical frame.
"""

from __future__ import annotations

import threading
import numpy as np

from octolog.schemas import posemsgs
from octolog.schemas.msgtypes import TFMessage

# camera_link (x forward, y left, z up) from an optical frame (x right, y down, z forward): REP 103
LINK_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0, 0, 0, 1.0]])
MAX_DEPTH = 16  # a tree, never a cycle: a longer chain is a loop in bad input


class StaticTree:
    """child -> (parent, parent_from_child) from tf2_msgs/TFMessage messages; thread-safe (a bus
    callback adds, the stage asks)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._parent: dict[str, tuple[str, np.ndarray]] = {}

    def add(self, msg: TFMessage) -> None:
        for parent, child, T in posemsgs.tf_transforms(msg):
            with self._lock:
                self._parent[child] = (parent, T)

    def root_from(self, frame: str, *, stop: str = "world") -> tuple[str, np.ndarray]:
        """(root, root_from_frame): up the static parents of `frame` to the first frame without one
        (or `stop`, which a stage attaches itself); (`frame`, identity) when it has none."""
        T = np.eye(4)
        with self._lock:
            for _ in range(MAX_DEPTH):
                if frame not in self._parent or self._parent[frame][0] == stop:
                    break
                parent, P = self._parent[frame]
                T, frame = P @ T, parent
        return frame, T
