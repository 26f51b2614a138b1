"""OpenCV calls whose results must not depend on the CPU's instruction set.

OpenCV picks some kernels at run time by the CPU's SIMD level (SSE4.1, AVX, AVX2, AVX-512 on x86-64).
Most of what octolog calls is bit-exact across those levels (FAST, the Harris response and angle of
ORB's detection, colour conversion, `solvePnPRansac`, `undistortPoints`, Hamming matching: checked
on TUM fr1/xyz with `OPENCV_CPU_DISABLE`), but two are not: the smoothing inside
`ORB.compute`, whose last-bit differences flip descriptor bits and, hundreds of frames later, the
trajectory, and bilinear `remap` (the synthetic scene's texture sampling). Those calls run inside
`baseline_simd()`, which switches OpenCV to its baseline code path (SSE2/SSE3 on x86-64, which every
x86-64 CPU runs the same way) for their duration only; detection, the costlier half of ORB, keeps
the dispatched kernels. docs/architecture.md ("Determinism", "Across machines") has the measurements.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import cv2

_lock = threading.Lock()


@contextlib.contextmanager
def baseline_simd() -> Iterator[None]:
    """OpenCV on its baseline (non-dispatched) code path inside the block, as it was before after it.

    `cv2.setUseOptimized` is process-wide: the lock keeps two threads of one process from restoring
    each other's setting half-way (octolog calls these from one thread per process).
    """
    with _lock:
        was = cv2.useOptimized()
        cv2.setUseOptimized(False)
        try:
            yield
        finally:
            cv2.setUseOptimized(was)
