"""RGB-D frames from an MCAP in the recorder's layout (what `octolog record` and `octolog import` write).

Colour (camera/color/image_raw, or its /compressed variant) and registered depth
(camera/aligned_depth_to_color/image_raw, or /compressed) are paired exactly as replay/tum.py pairs a
TUM folder: nearest stamps, each image used once, closer than 20 ms. seq is the pair index, the stamp
is the colour image's. Intrinsics come from the colour camera_info; the depth scale from the
"calibration" metadata record (0.001 m per unit, the ROS 16UC1 convention, when the file has none).
A file with raw depth only (camera/depth/image_rect_raw: a RealSense Viewer recording imported, or
`record --depth-streams raw`) is registered to colour on the fly (octolog.kit.registration) with
the depth camera_info and the recording's `color_from_depth` extrinsics.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from octolog.kit.calibration import Calibration
from octolog.kit.errors import InputError
from octolog.kit.geometry import Intrinsics, RgbdFrame
from octolog.kit.mcaplog import damaged, read_messages, summarize
from octolog.kit.registration import register_depth
from octolog.kit.tum import MAX_PAIR_DT_NS, associate
from octolog.replay.source_gravity import recorded_up
from octolog.schemas import codec, imagecodec, sensormsgs
from octolog.schemas.msgtypes import CompressedImage, Image
from octolog.schemas.topics import (
    ALIGNED_DEPTH,
    ALIGNED_DEPTH_INFO,
    ALIGNED_DEPTH_PNG,
    COLOR,
    COLOR_INFO,
    COLOR_JPEG,
    DEPTH,
    DEPTH_INFO,
    DEPTH_PNG,
    Topic,
)

DEFAULT_DEPTH_SCALE_M = 0.001
# Topics that make a file replayable as RGB-D frames (any colour variant + any aligned depth variant).
COLOR_TOPICS = (COLOR, COLOR_JPEG)
DEPTH_TOPICS = (ALIGNED_DEPTH, ALIGNED_DEPTH_PNG)
RAW_DEPTH_TOPICS = (DEPTH, DEPTH_PNG)  # registered to colour on reading (module docstring)


@dataclass(frozen=True)
class StandardSequence:
    """An opened recorder-layout MCAP: the paired frame list, ready to be read in order."""

    path: Path
    color: Topic
    depth: Topic
    pairs: tuple[tuple[int, int], ...]  # (colour message index, depth message index) on their topics
    color_stamps: tuple[int, ...]
    intrinsics: Intrinsics
    depth_scale_m: float
    depth_scale_source: str
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    # raw depth: its camera's intrinsics and color_from_depth (4x4), to register it to colour
    registration: tuple[Intrinsics, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def duration_ns(self) -> int:
        return self.color_stamps[self.pairs[-1][0]] - self.color_stamps[self.pairs[0][0]] if self.pairs else 0

    def groundtruth_tum(self) -> str | None:
        return self.metadata.get("groundtruth", {}).get("tum")

    def gravity_up(self) -> np.ndarray | None:
        """Up at the first frame from the recording's accelerometer (octolog.replay.source_gravity)."""
        if not self.pairs:
            return None
        frame = next(iter(self.frames(0, 1)))
        return recorded_up(self.path, self.color_stamps[self.pairs[0][0]], frame.frame_id)

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
        """Frames start..end in pair order; reads the file once, holding only images not yet paired."""
        todo = list(enumerate(self.pairs[start:end], start))
        if not todo:
            return
        want_c = {ci: seq for seq, (ci, _) in todo}
        want_d = {di: seq for seq, (_, di) in todo}
        got_c: dict[int, bytes] = {}
        got_d: dict[int, bytes] = {}
        n_c = n_d = 0
        nxt = 0
        for m in read_messages(self.path, [self.color.name, self.depth.name]):
            if m.topic == self.color.name:
                if n_c in want_c:
                    got_c[want_c[n_c]] = m.data
                n_c += 1
            else:
                if n_d in want_d:
                    got_d[want_d[n_d]] = m.data
                n_d += 1
            while nxt < len(todo) and todo[nxt][0] in got_c and todo[nxt][0] in got_d:
                seq = todo[nxt][0]
                yield self._frame(seq, got_c.pop(seq), got_d.pop(seq))
                nxt += 1
            if nxt == len(todo):
                return
        raise InputError(f"{self.path}: frame {todo[nxt][0]}: image missing on a second read (file changed?)")

    def _frame(self, seq: int, color_data: bytes, depth_data: bytes) -> RgbdFrame:
        try:
            cmsg = codec.decode(color_data, self.color.msgtype)
            dmsg = codec.decode(depth_data, self.depth.msgtype)
            rgb = _pixels(cmsg)
            depth = _pixels(dmsg)
        except InputError as exc:
            raise InputError(f"{self.path}: frame {seq}: {exc}") from None
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise InputError(f"{self.path}: frame {seq}: /{self.color.name} is not 8-bit colour")
        if depth.ndim != 2 or depth.dtype != np.uint16:
            raise InputError(f"{self.path}: frame {seq}: /{self.depth.name} is not 16-bit depth")
        intr = self.intrinsics
        if self.registration is not None:
            depth_k, color_from_depth = self.registration
            if depth.shape != (depth_k.height, depth_k.width):
                raise InputError(f"{self.path}: frame {seq}: depth {depth.shape[1]}x{depth.shape[0]}, its camera_info "
                                 f"{depth_k.width}x{depth_k.height}")
            depth = register_depth(depth, depth_k, intr, color_from_depth, self.depth_scale_m)
        if rgb.shape[:2] != depth.shape or depth.shape != (intr.height, intr.width):
            raise InputError(f"{self.path}: frame {seq}: sizes disagree: colour {rgb.shape[1]}x{rgb.shape[0]}, "
                             f"depth {depth.shape[1]}x{depth.shape[0]}, camera_info {intr.width}x{intr.height}")
        return RgbdFrame(seq=seq, stamp_ns=codec.stamp_ns(cmsg.header), rgb=np.array(rgb), depth=np.array(depth),
                         depth_scale_m=self.depth_scale_m, intrinsics=intr,
                         frame_id=cmsg.header.frame_id or RgbdFrame.__dataclass_fields__["frame_id"].default)


def _pixels(msg: Image | CompressedImage) -> np.ndarray:
    if isinstance(msg, CompressedImage):
        return imagecodec.decode_compressed_image(msg)
    return sensormsgs.image_array(msg)


def _header_stamp(data: bytes) -> int:
    """The header stamp of a CDR Image/CompressedImage without decoding its pixels."""
    if len(data) < 12:
        raise InputError(f"message of {len(data)} bytes: too short for a header")
    endian = "<" if data[1] == 1 else ">"
    sec, nsec = struct.unpack_from(endian + "iI", data, 4)
    return sec * 1_000_000_000 + nsec


def open_standard(path: str | Path, calibration: Calibration | None = None, *,
                  max_dt_ns: int = MAX_PAIR_DT_NS) -> StandardSequence:
    """Open a recorder-layout MCAP and pair its frames; InputError says what is missing."""
    path = Path(path)
    summary = summarize(path)
    if not summary.complete:
        raise InputError(damaged(path, summary.problem))
    topics = summary.topics
    color = next((t for t in COLOR_TOPICS if t.name in topics), None)
    depth = next((t for t in DEPTH_TOPICS if t.name in topics), None)
    if color is None:
        raise InputError(f"{path}: /{COLOR.name} missing: no colour images "
                         f"(topics: {', '.join(sorted(topics)) or 'none'})")
    registration = None
    if depth is None:
        depth = next((t for t in RAW_DEPTH_TOPICS if t.name in topics), None)
        if depth is None:
            raise InputError(f"{path}: no depth images: neither /{ALIGNED_DEPTH.name} nor /{DEPTH.name} "
                             f"(topics: {', '.join(sorted(topics))})")
        registration = _registration(path, topics, summary.metadata.get("calibration", {}), depth)
    for t in (color, depth):
        if topics[t.name].msgtype != t.msgtype:
            raise InputError(f"{path}: /{t.name} holds {topics[t.name].msgtype}, want {t.msgtype}")
    info_topic = next((t for t in (COLOR_INFO, ALIGNED_DEPTH_INFO) if t.name in topics), None)
    if info_topic is None and calibration is None:
        raise InputError(f"{path}: missing calibration: no /{COLOR_INFO.name} or /{ALIGNED_DEPTH_INFO.name}; "
                         f"give one with --set replay.camera=CAMERA.toml (docs/formats.md)")

    c_stamps: list[int] = []
    d_stamps: list[int] = []
    info = calibration.intrinsics if calibration is not None and info_topic is None else None
    for m in read_messages(path, [color.name, depth.name] + ([info_topic.name] if info_topic else [])):
        try:
            if m.topic == color.name:
                c_stamps.append(_header_stamp(m.data))
            elif m.topic == depth.name:
                d_stamps.append(_header_stamp(m.data))
            elif info is None:
                info = sensormsgs.intrinsics_from(codec.decode(m.data, info_topic.msgtype))
        except InputError as exc:
            raise InputError(f"{path}: /{m.topic}: {exc}") from None
    if info is None:
        raise InputError(f"{path}: missing calibration: /{info_topic.name if info_topic else COLOR_INFO.name} "
                         f"has no messages")

    # associate() wants sorted stamps; files written in time order are already sorted.
    c_order = sorted(range(len(c_stamps)), key=c_stamps.__getitem__)
    d_order = sorted(range(len(d_stamps)), key=d_stamps.__getitem__)
    pairs = associate([c_stamps[i] for i in c_order], [d_stamps[i] for i in d_order], max_dt_ns)
    if not pairs:
        gap = min((abs(c - d) for c in c_stamps for d in d_stamps), default=0)
        raise InputError(f"{path}: no colour/depth pairs within {max_dt_ns / 1e6:g} ms ({len(c_stamps)} colour, "
                         f"{len(d_stamps)} depth images, the closest {gap / 1e6:.0f} ms apart; a wider window: "
                         f"--set replay.pair_ms=MS)")

    scale, source = _depth_scale(path, summary.metadata.get("calibration", {}), calibration)
    return StandardSequence(
        path=path, color=color, depth=depth,
        pairs=tuple((c_order[i], d_order[k]) for i, k in pairs),
        color_stamps=tuple(c_stamps), intrinsics=info, depth_scale_m=scale, depth_scale_source=source,
        metadata=summary.metadata, registration=registration,
    )


def _registration(path: Path, topics: Collection[str], calib: dict[str, str],
                  depth: Topic) -> tuple[Intrinsics, np.ndarray]:
    """What registering raw depth to colour takes: the depth camera_info's intrinsics and the
    calibration's `color_from_depth` (`octolog record`: a JSON 4x4; `octolog import`: 12 numbers,
    3x4 row-major); InputError names what is missing."""
    if DEPTH_INFO.name not in topics:
        raise InputError(f"{path}: raw depth /{depth.name} without /{DEPTH_INFO.name}: cannot register it to colour")
    text = calib.get("color_from_depth", "")
    try:
        values = np.array(json.loads(text) if text.lstrip().startswith("[") else text.split(), dtype=np.float64)
        T = np.vstack([values.reshape(-1, 4)[:3], [0.0, 0.0, 0.0, 1.0]])
        if values.size not in (12, 16) or not np.isfinite(T).all():
            raise ValueError(text)
    except ValueError:
        raise InputError(f"{path}: raw depth /{depth.name} without the depth-to-colour extrinsics (calibration "
                         f"color_from_depth {text[:60]!r}): cannot register it to colour") from None
    for m in read_messages(path, [DEPTH_INFO.name]):
        try:
            return sensormsgs.intrinsics_from(codec.decode(m.data, DEPTH_INFO.msgtype)), T
        except InputError as exc:
            raise InputError(f"{path}: /{m.topic}: {exc}") from None
    raise InputError(f"{path}: /{DEPTH_INFO.name} has no messages: cannot register raw depth to colour")


def _depth_scale(path: Path, calib: dict[str, str], calibration: Calibration | None) -> tuple[float, str]:
    """Metres per depth unit and where that came from: a calibration file given wins, then the
    recording's calibration metadata, then the ROS 16UC1 convention (1 mm)."""
    scale_text = calib.get("depth_scale_m")
    if calibration is not None and calibration.depth_scale_m is not None:  # the file given wins
        return calibration.depth_scale_m, f"calibration file ({calibration.name})"
    if scale_text is None:
        return (DEFAULT_DEPTH_SCALE_M,
                f"default {DEFAULT_DEPTH_SCALE_M} m per unit (ROS 16UC1 convention): no calibration depth_scale_m")
    try:
        scale = float(scale_text)
    except ValueError:
        raise InputError(f"{path}: calibration depth_scale_m {scale_text!r} is not a number") from None
    if not scale > 0:
        raise InputError(f"{path}: calibration depth_scale_m {scale_text!r}: want > 0 metres per unit")
    return scale, calib.get("depth_scale_source", "calibration metadata")


def read_standard_frames(path: str | Path, *, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
    """Paired RGB-D frames start..end of a recorder-layout MCAP (seq = pair index, stamp = colour's)."""
    return open_standard(path).frames(start, end)


def count_standard_frames(path: str | Path) -> int:
    """How many colour/depth pairs read_standard_frames would give."""
    return len(open_standard(path))


def has_standard_frames(topics: Collection[str]) -> bool:
    """Whether a file with these topics (McapSummary.topics) holds colour and depth (aligned, or raw
    to register)."""
    return any(t.name in topics for t in COLOR_TOPICS) and \
        any(t.name in topics for t in (*DEPTH_TOPICS, *RAW_DEPTH_TOPICS))
