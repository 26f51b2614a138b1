"""The width and height a PNG, JPEG or zstd depth image declares in its own header, read without
decoding the image.

A PNG or JPEG can claim a 10^9-pixel image in 30 bytes, and decoding it would allocate gigabytes:
readers ask here first (schemas.checks at the bus, rgbdmsgs before decoding a frame's images).
"""

from __future__ import annotations

import struct

_PNG = b"\x89PNG\r\n\x1a\n"
# octolog's zstd depth (schemas.imagecodec.depth_zstd): the magic, then width and height as little-endian uint32
ZSTD_DEPTH_MAGIC = b"ZSUB"
ZSTD_DEPTH_HEADER = 12
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def declared_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR, a JPEG's start-of-frame segment or a zstd depth image's
    header; None if `data` does not start like any of them."""
    data = bytes(data[:65536])  # the header, never the whole image
    if data.startswith(_PNG) and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return w, h
    if data.startswith(b"\xff\xd8"):
        return _jpeg_size(data)
    if data.startswith(ZSTD_DEPTH_MAGIC) and len(data) >= ZSTD_DEPTH_HEADER:
        w, h = struct.unpack("<II", data[4:ZSTD_DEPTH_HEADER])
        return w, h
    return None


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """Width and height from a JPEG's start-of-frame segment, walking the segments before it."""
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
            i += 2
            continue
        length = struct.unpack(">H", data[i + 2:i + 4])[0]
        if length < 2:
            return None
        if marker in _JPEG_SOF:
            if i + 9 > len(data):
                return None
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        i += 2 + length
    return None
