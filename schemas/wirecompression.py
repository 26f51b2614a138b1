"""The wire-compression spec: how a producer compresses images on the wire, parsed from config text.

Cheap to import (no rosbags, no OpenCV): a process parsing its config does not pay for the codec.
"""

from __future__ import annotations

from dataclasses import dataclass

from octolog.kit.errors import ConfigError


@dataclass(frozen=True)
class WireCompression:
    """How a producer compresses images on the wire: colour "jpeg" (lossy, `quality` 1-100) or "png"
    (lossless, zlib `level` 0-9); depth "png" or "zstd" (`depth_zstd`), both lossless in sensor units."""

    colour: str = "jpeg"
    quality: int = 90
    level: int = 1
    depth: str = "png"

    @property
    def colour_format(self) -> str:
        return f"rgb8; {self.colour} compressed bgr8"


DEPTH_PNG_FORMAT = "16UC1; png compressed"
DEPTH_ZSTD_FORMAT = "16UC1; zstd sub compressed"
DEPTH_CODECS = {"png": DEPTH_PNG_FORMAT, "zstd": DEPTH_ZSTD_FORMAT}


SOURCE = "source"  # frames as the source encodes them; keyframes as the frames came


def parse_wire_compression(spec: str) -> WireCompression | None:
    """`"source"`, `""`, `"raw"`: no re-encoding (the caller passes encoded images on as they are,
    or sends raw ones); else `COLOUR[,DEPTH]` with COLOUR `jpeg[:QUALITY]` or `png[:LEVEL]`
    and DEPTH `png` (the default) or `zstd` (`depth_zstd`; depth is never compressed lossily)."""
    if spec in (SOURCE, "", "raw"):
        return None
    colour, _, depth = spec.partition(",")
    depth = depth or "png"
    if depth not in DEPTH_CODECS:
        raise ConfigError(f"wire compression {spec!r}: depth can be png or zstd (lossless), got {depth!r}")
    kind, _, arg = colour.partition(":")
    try:
        value = int(arg) if arg else None
    except ValueError:
        raise ConfigError(f"wire compression {spec!r}: {arg!r} is not an integer") from None
    if kind == "jpeg" and (value is None or 1 <= value <= 100):
        return WireCompression("jpeg", quality=value or 90, depth=depth)
    if kind == "png" and (value is None or 0 <= value <= 9):
        return WireCompression("png", level=1 if value is None else value, depth=depth)
    raise ConfigError(f"wire compression {spec!r}: want raw, or jpeg[:1-100] or png[:0-9] for colour, "
                      f"optionally followed by ,png or ,zstd for depth")
