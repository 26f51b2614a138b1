"""octolog: log-based record/replay toolkit for real-time RGB-D indoor mapping."""

from __future__ import annotations

import os
import platform

__version__ = "0.1.0"

# Determinism across machines (docs/architecture.md): OpenBLAS, loaded with numpy, picks its kernels
# by CPU, and its FMA kernels (Haswell and later) round matrix products differently from its SSE
# ones, which reaches the tracker's poses. Every x86-64 CPU that runs numpy 2 has SSE4.2, so an
# octolog process pins OpenBLAS's Nehalem (SSE4.2) kernels: no measurable cost here, the same bytes
# on every x86-64 CPU. It takes effect when octolog is imported before numpy (every octolog
# process, the tests' conftest); OCTOLOG_OPENBLAS_CORETYPE picks another core ("auto": OpenBLAS's).
_X86 = platform.machine().lower() in ("x86_64", "amd64")
_CORE = os.environ.get("OCTOLOG_OPENBLAS_CORETYPE", "Nehalem")
if _CORE != "auto" and _X86:
    os.environ["OPENBLAS_CORETYPE"] = _CORE

# The same for numpy's own loops: on a CPU with AVX-512, numpy 2 dispatches float64 log, exp, power,
# arccos, arctan (and float32 log2, ...) to AVX-512 implementations whose last bits differ from the
# AVX2 ones, which reached the tracker (sigma = 1.2 ** octave) and the synthetic renderer (log2 of the
# texture footprint). An octolog process turns numpy's AVX-512 dispatch off, so an AVX-512 machine
# computes what an AVX2 machine does (tests/shell/test_determinism.py). Elementwise arithmetic, sums and
# sqrt are exact at every level and keep their speed. OCTOLOG_NUMPY_DISABLE names other features
# ("auto": numpy's own choice); features a CPU lacks are ignored.
_NPY = os.environ.get("OCTOLOG_NUMPY_DISABLE", "X86_V4 AVX512_ICL AVX512_SPR")
if _NPY != "auto" and _X86:
    _have = os.environ.get("NPY_DISABLE_CPU_FEATURES", "").replace(",", " ").split()
    os.environ["NPY_DISABLE_CPU_FEATURES"] = " ".join(dict.fromkeys(_have + _NPY.split()))

# One BLAS thread per process. octolog's matrices are small (a local BA's reduced system is 30x30, its
# camera-by-point blocks 60x2400) and each stage is its own process on a machine of a few cores:
# OpenBLAS's worker threads bought no speed and spun between calls, which more than doubled the
# tracker's CPU time per frame on 2 cores (bench/tracker.py, fast case: 6.7 -> 4.0 s). An explicit
# OPENBLAS_NUM_THREADS is respected.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# glibc's allocator hands large blocks (a frame's arrays: 1-10 MB each) back to the kernel when they
# are freed, and the next frame's arrays are fresh pages the kernel must fault in and zero again: a
# rendered synthetic frame took ~8,900 page faults. An octolog process keeps freed memory for reuse
# instead: blocks up to 32 MB come from the heap, and its free top is returned only beyond 512 MB
# (the same frame then takes none; per-frame CPU 10-20 % lower here, a process's resident size
# stays near its peak). OCTOLOG_MALLOC=default leaves glibc's own policy; other C libraries are left alone.
if os.environ.get("OCTOLOG_MALLOC") != "default" and platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
    import ctypes

    _libc = ctypes.CDLL(None)
    _M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
    _libc.mallopt(_M_MMAP_THRESHOLD, 32 * 2**20)
    _libc.mallopt(_M_TRIM_THRESHOLD, 512 * 2**20)
