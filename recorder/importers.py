"""`octolog import`: a TUM RGB-D folder, a RealSense or other ROS 1/ROS 2 bag into an MCAP in the
recorder's layout (see import_output), so replay reads an import exactly as it reads a recording.

`import_source` tells the kind of source apart and hands it to tum_import or bag_import.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

from octolog.kit.errors import InputError
from octolog.recorder.bag_import import import_bag
from octolog.recorder.import_output import ImportResult, detect_kind
from octolog.recorder.tum_import import import_tum


def import_source(source: str | Path, output: Path, *, overwrite: bool = False,
                  topic_map: dict[str, str] | None = None, compression: str = "zstd",
                  depth_scale_m: float | None = None, camera: str = "",
                  progress: Callable[[int], None] | None = None) -> ImportResult:
    """Import a TUM folder or a ROS 1/ROS 2 bag (RealSense or other) into an MCAP in the recorder's layout."""
    source = Path(source)
    kind = detect_kind(source)
    if kind == "tum":
        if topic_map:
            raise InputError(f"{source}: --map applies to bags, not to a TUM folder")
        return import_tum(source, output, overwrite=overwrite, compression=compression, camera=camera,
                          progress=progress)
    if camera:
        raise InputError(f"{source}: --camera names a TUM folder's camera; a bag carries its own calibration")
    return import_bag(source, output, overwrite=overwrite, topic_map=topic_map, compression=compression,
                      depth_scale_m=depth_scale_m, progress=progress)


def parse_topic_map(items: Iterable[str]) -> dict[str, str]:
    """`SRC=DST` strings (the CLI's repeated --map) as a dict; source names keep their leading slash."""
    out: dict[str, str] = {}
    for item in items:
        src, sep, dst = item.partition("=")
        if not sep or not src.strip() or not dst.strip():
            raise InputError(f"--map {item!r}: want SOURCE_TOPIC=TARGET_TOPIC")
        src = "/" + src.strip().lstrip("/")
        if src in out:
            raise InputError(f"--map {item!r}: {src} mapped twice")
        out[src] = dst.strip().strip("/")
    return out
