"""Prints hashes of what the CPU's instruction set could change: rendered frames, ORB features, poses.

Run as a script by tests/shell/test_determinism.py under restricted instruction sets (OPENCV_CPU_DISABLE,
NPY_DISABLE_CPU_FEATURES, OPENBLAS_CORETYPE) and compared with an unrestricted run. Not collected by
pytest (no test_ prefix).

usage: python tests/isa_probe.py SOURCE FRAMES   (SOURCE: synthetic:N[:imu=HZ...] or tum:PATH)
OCTOLOG_PROBE_CV_UNOPTIMIZED=1: with cv2.setUseOptimized(False) for the whole run.
"""

from __future__ import annotations

# isort: off
import octolog  # noqa: F401  (before numpy: pins OpenBLAS's kernels, as in every octolog process)
# isort: on
import ctypes
import hashlib
import os
import sys
from pathlib import Path

import numpy as np

from octolog.replay.imu import source_imu
from octolog.replay.sources import open_source
from octolog.tracker.config import TrackerConfig, for_source
from octolog.tracker.factory import make_odometry
from octolog.tracker.features import OrbExtractor, grey_image


def main(source: str, n_frames: int) -> None:
    if os.environ.get("OCTOLOG_PROBE_CV_UNOPTIMIZED"):
        import cv2

        cv2.setUseOptimized(False)
    src = open_source(source)
    cfg = for_source(TrackerConfig(background=False), src)
    f = cfg.odometry_params().features
    extractor = OrbExtractor(n_features=cfg.n_features, grid_cols=f.grid_cols, grid_rows=f.grid_rows,
                             fast_threshold=f.fast_threshold, min_fast_threshold=f.min_fast_threshold,
                             n_levels=f.n_levels, scale_factor=f.scale_factor)
    odometry = make_odometry(cfg)
    h = {name: hashlib.sha256() for name in ("frames", "features", "poses")}
    imu, last_ns = source_imu(src), None  # with one, the IMU's samples up to each frame, as the replay sends them
    for i, frame in enumerate(src.frames()):
        if i >= n_frames:
            break
        if imu is not None:
            odometry.add_imu(imu.samples.between(frame.stamp_ns - 50_000_000 if last_ns is None else last_ns,
                                                 frame.stamp_ns))
            last_ns = frame.stamp_ns
        h["frames"].update(frame.rgb.tobytes() + frame.depth.tobytes())
        for a in extractor.extract(grey_image(frame)):
            h["features"].update(np.ascontiguousarray(a).tobytes())
        h["poses"].update(np.ascontiguousarray(odometry.track(frame).world_from_camera).tobytes())
    odometry.finish()
    _, poses = odometry.trajectory()
    h["poses"].update(np.ascontiguousarray(poses).tobytes())
    if imu is not None:
        h["poses"].update(repr(odometry.imu_state).encode())
    for name, digest in h.items():
        print(name, digest.hexdigest())
    print("openblas", openblas_core())


def openblas_core() -> str:
    """The kernel set numpy's OpenBLAS runs with (its own report; "?" if it has no such call)."""
    for lib in sorted((Path(np.__file__).parent.parent / "numpy.libs").glob("libscipy_openblas*")):
        get = getattr(ctypes.CDLL(str(lib)), "scipy_openblas_get_corename64_", None)
        if get is not None:
            get.restype = ctypes.c_char_p
            return get().decode()
    return "?"


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]))
