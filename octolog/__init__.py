"""octolog: log-based record/replay toolkit for real-time RGB-D indoor mapping."""

from __future__ import annotations

__version__ = "0.1.0"
