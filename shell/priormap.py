"""`octolog run --map`: the saved map a session tracks in, checked before any process starts, and the
mapper that starts from that session's map (mapper/prior.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from octolog.kit.errors import InputError
from octolog.mapper.config import MapperConfig
from octolog.replay.sources import Source
from octolog.tracker.mapfile import load_map


def check_prior(path: str, src: Source | Any, source: str) -> None:
    """A saved map the session can track in: readable, and of the source's camera (a file source's
    first frame); InputError naming the problem, before any process starts."""
    saved = load_map(path)
    if not hasattr(src, "frames") or len(src) == 0:
        return
    intr = next(iter(src.frames(0, 1))).intrinsics
    if intr != saved.intrinsics:
        raise InputError(f"--map {path}: a map of another camera ({saved.intrinsics}) than {source}'s ({intr})")


def prior_mapper(cfg: MapperConfig, folder: Path) -> MapperConfig:
    """The mapper of a session tracked in `folder`'s saved map: it starts from that session's map, in
    that session's frame, once the tracker shows it found the camera there (mapper/prior.py), unless
    the config names another prior; a bare map file (no session log beside it) gives no prior."""
    if cfg.prior or not (folder / "session.mcap").is_file():
        return cfg
    return dataclasses.replace(cfg, prior=str(folder.resolve()))
