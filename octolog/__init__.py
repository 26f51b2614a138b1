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
_CORE = os.environ.get("OCTOLOG_OPENBLAS_CORETYPE", "Nehalem")
if _CORE != "auto" and platform.machine().lower() in ("x86_64", "amd64"):
    os.environ["OPENBLAS_CORETYPE"] = _CORE
