"""The versions a session records (summary.json): octolog's, Python's and the pinned dependencies'.

Apart from shell/run.py so that `octolog record` can write them without importing the pipeline.
"""

from __future__ import annotations

import sys
from importlib.metadata import PackageNotFoundError, version

from octolog import __version__

PINNED = ("eclipse-zenoh", "mcap", "rerun-sdk", "numpy", "scipy", "opencv-python-headless", "open3d-cpu",
          "pyoctomap", "rosbags", "pyrealsense2", "gtsam", "pyorbslam3")


def versions() -> dict[str, str]:
    """octolog's, Python's and the pinned dependencies' versions, for summary.json and metadata."""
    out = {"octolog": __version__, "python": sys.version.split()[0]}
    for name in PINNED:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "missing"
    return out
