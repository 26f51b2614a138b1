"""TUM RGB-D folders (the kit's reader, shared by the replay source and `octolog import`): rgb.txt, depth.txt,
PNG images and an optional groundtruth.txt.

Colour and depth are paired by nearest timestamp within 20 ms (as the TUM tools do); depth keeps
its units (5000 per metre). Intrinsics come from the sequence name (freiburg1/2/3, the ROS default
calibration most evaluations use) unless given explicitly.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from octolog.kit.errors import InputError
from octolog.kit.geometry import EncodedRgbd, Intrinsics, RgbdFrame

T = TypeVar("T")

TUM_DEPTH_SCALE_M = 1.0 / 5000.0
MAX_PAIR_DT_NS = 20_000_000

# The calibration of the TUM benchmark's three Kinects (ROS default intrinsics, 640x480).
TUM_INTRINSICS = {
    "freiburg1": Intrinsics(
        640, 480, 517.306408, 516.469215, 318.643040, 255.313989,
        (0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
    ),
    "freiburg2": Intrinsics(
        640, 480, 520.908620, 521.007327, 325.141442, 249.701764,
        (0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
    ),
    "freiburg3": Intrinsics(640, 480, 535.4, 539.2, 320.1, 247.6, ()),
}

# Rolling-shutter readout time of the colour camera (first row to last, s). freiburg1: picked on
# fr1/xyz first300 by the tracker's own reprojection residual, no ground truth (bench/readout.py;
# docs/architecture.md). freiburg2/3 are unmeasured here: 0 (no correction) until someone measures them.
TUM_READOUT_S = {"freiburg1": 0.020}


def seconds_to_ns(text: str) -> int:
    """Exact integer nanoseconds of a decimal seconds string (no float rounding); ValueError for a
    stamp that is not a finite number of seconds that fits in int64 nanoseconds (about 292 years)."""
    value = Decimal(text)
    if not value.is_finite() or abs(value) >= 9_223_372_036:
        raise ValueError(f"stamp {text!r} out of range")
    return int((value * 1_000_000_000).to_integral_value())


def read_rows(path: Path, parse: Callable[[list[str]], T], want: str) -> list[T]:
    """Parse every non-comment line of a TUM text file; a bad line raises InputError naming it."""
    rows = []
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:  # found by tests/kit/test_fuzz.py
        raise InputError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            rows.append(parse(line.split()))
        except (InvalidOperation, ValueError, IndexError, OverflowError):
            raise InputError(f"{path}:{lineno}: malformed line {line!r} (want '{want}')") from None
    return rows


def read_list(path: Path) -> list[tuple[int, str]]:
    if not path.is_file():
        raise InputError(f"{path}: missing (a TUM RGB-D folder needs rgb.txt and depth.txt)")

    def parse(parts: list[str]) -> tuple[int, str]:
        if len(parts) != 2:
            raise ValueError
        return seconds_to_ns(parts[0]), parts[1]

    rows = read_rows(path, parse, "timestamp file")
    if not rows:
        raise InputError(f"{path}: lists no images")
    return rows


def associate(a: list[int], b: list[int], max_dt_ns: int = MAX_PAIR_DT_NS) -> list[tuple[int, int]]:
    """Pair indices of two sorted stamp lists, nearest first, each used once (TUM associate.py)."""
    a_arr, b_arr = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    cands = []
    for i, t in enumerate(a_arr):
        j = int(np.searchsorted(b_arr, t))
        for k in (j - 1, j):
            if 0 <= k < len(b_arr):
                dt = abs(int(b_arr[k]) - int(t))
                if dt < max_dt_ns:
                    cands.append((dt, i, k))
    cands.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, k in cands:
        if i not in used_a and k not in used_b:
            used_a.add(i)
            used_b.add(k)
            pairs.append((i, k))
    pairs.sort()
    return pairs


TUM_CAMERAS = tuple(TUM_INTRINSICS)  # freiburg1, freiburg2, freiburg3


def camera_for(folder: Path, camera: str = "") -> str:
    """The TUM camera that took `folder`: `camera` when given, else the one its name says (as the
    benchmark names its sequences, `rgbd_dataset_freiburg3_...`). Never a guess: a name that says
    none (a renamed folder, another dataset in TUM layout) is an error naming the options."""
    if camera:
        if camera not in TUM_INTRINSICS:
            raise InputError(f"camera {camera!r}: want one of {', '.join(TUM_CAMERAS)} or a calibration file (.toml)")
        return camera
    name = Path(os.path.abspath(folder)).name  # the name the user gave (a symlink's, not its target's)
    found = [key for key in TUM_CAMERAS if key in name]
    if len(found) != 1:
        raise InputError(f"{folder}: the folder name does not say which camera took it ({', '.join(TUM_CAMERAS)}); "
                         "name it with --set replay.camera=freiburgN or a calibration file, "
                         "--set replay.camera=CAMERA.toml (octolog run/replay), or --camera freiburgN (octolog import)")
    return found[0]


def readout_for(camera: str) -> float:
    """The colour camera's rolling-shutter readout time in s (0: not measured, no correction)."""
    return TUM_READOUT_S.get(camera, 0.0)


@dataclass(frozen=True)
class TumSequence:
    """An opened TUM folder: the paired frame list, ready to be read in order."""

    folder: Path
    pairs: tuple[tuple[int, str, int, str], ...]  # (rgb_ns, rgb_file, depth_ns, depth_file)
    intrinsics: Intrinsics
    groundtruth: Path | None
    camera: str  # freiburg1/2/3, or "" when the intrinsics were given instead
    depth_scale_m: float = 1.0 / 5000.0  # TUM's; a calibration file may say otherwise

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def duration_ns(self) -> int:
        return self.pairs[-1][0] - self.pairs[0][0] if self.pairs else 0

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
        for seq, (rgb_ns, rgb_file, _depth_ns, depth_file) in enumerate(self.pairs[start:end], start):
            rgb = read_png(self.folder / rgb_file, cv2.IMREAD_COLOR)
            depth = read_png(self.folder / depth_file, cv2.IMREAD_ANYDEPTH)
            if rgb.ndim != 3 or rgb.shape[2] != 3:
                raise InputError(f"{self.folder / rgb_file}: not a 3-channel colour image")
            if depth.dtype != np.uint16 or depth.ndim != 2:
                raise InputError(f"{self.folder / depth_file}: depth must be a 16-bit single-channel PNG")
            if rgb.shape[:2] != depth.shape:
                raise InputError(f"{self.folder / depth_file}: size {depth.shape} differs from colour {rgb.shape[:2]}")
            yield RgbdFrame(
                seq=seq,
                stamp_ns=rgb_ns,
                rgb=cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB),
                depth=depth,
                depth_scale_m=self.depth_scale_m,
                intrinsics=self.intrinsics,
            )


    def encoded_frames(self, start: int = 0, end: int | None = None) -> Iterator[EncodedRgbd]:
        """The pairs as their PNG files hold them, not decoded: each file's header is checked
        (colour 8-bit RGB, depth 16-bit grey, sizes agreeing with the camera) and its end present,
        so a missing, truncated or wrong image is still an error naming the file, here."""
        for seq, (rgb_ns, rgb_file, _depth_ns, depth_file) in enumerate(self.pairs[start:end], start):
            rgb, rgb_size = read_png_bytes(self.folder / rgb_file, 8, PNG_RGB, "an 8-bit RGB")
            depth, depth_size = read_png_bytes(self.folder / depth_file, 16, PNG_GREY, "a 16-bit single-channel")
            if rgb_size != depth_size:
                raise InputError(f"{self.folder / depth_file}: size {depth_size[::-1]} differs from colour {rgb_size[::-1]}")
            yield EncodedRgbd(seq, rgb_ns, rgb, PNG_COLOUR_FORMAT, depth, PNG_DEPTH_FORMAT,
                              self.depth_scale_m, self.intrinsics)


# PNG colour types (IHDR) and the image_transport format strings of PNG colour and depth
PNG_GREY, PNG_RGB = 0, 2
PNG_COLOUR_FORMAT = "rgb8; png compressed bgr8"
PNG_DEPTH_FORMAT = "16UC1; png compressed"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def png_header(data: bytes) -> tuple[int, int, int, int] | None:
    """(width, height, bit depth, colour type) of a PNG's IHDR, or None if `data` is not a PNG."""
    if len(data) < 33 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        return None
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return width, height, data[24], data[25]


def read_png_bytes(path: Path, bits: int, colour_type: int, want: str) -> tuple[bytes, tuple[int, int]]:
    """A PNG file's bytes and (width, height), checked without decoding: header, kind and end marker."""
    if not path.is_file():
        raise InputError(f"{path}: image listed but missing")
    data = path.read_bytes()
    head = png_header(data)
    if head is None:
        raise InputError(f"{path}: unreadable image (corrupt or not a PNG)")
    if not data.endswith(_PNG_END):
        raise InputError(f"{path}: truncated PNG (no end marker)")
    if head[2:] != (bits, colour_type):
        raise InputError(f"{path}: want {want} PNG, got bit depth {head[2]}, colour type {head[3]} "
                         "(--set replay.wire_compression=raw decodes and converts it)")
    return data, head[:2]


def read_png(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path}: image listed but missing")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise InputError(f"{path}: unreadable image (corrupt or not a PNG)")
    return img


def open_tum(folder: str | Path, intrinsics: Intrinsics | None = None, *, camera: str = "") -> TumSequence:
    """Open a TUM RGB-D folder taken by `camera` (default: the one its name says), or with `intrinsics`;
    raises InputError naming the file that is missing or malformed, or the camera nobody named."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder (want a TUM RGB-D sequence folder)")
    rgb = read_list(folder / "rgb.txt")
    depth = read_list(folder / "depth.txt")
    pairs = associate([t for t, _ in rgb], [t for t, _ in depth])
    if not pairs:
        raise InputError(f"{folder}: no colour/depth pairs within 20 ms")
    if intrinsics is None:
        camera = camera_for(folder, camera)
        intrinsics = TUM_INTRINSICS[camera]
    gt = folder / "groundtruth.txt"
    return TumSequence(
        folder=folder,
        pairs=tuple((rgb[i][0], rgb[i][1], depth[k][0], depth[k][1]) for i, k in pairs),
        intrinsics=intrinsics,
        groundtruth=gt if gt.is_file() else None,
        camera=camera,
    )
