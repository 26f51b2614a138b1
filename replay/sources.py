"""Frame sources for replay: a TUM RGB-D folder, an octolog MCAP file, or the synthetic scene.

A source spec is `tum:PATH`, `mcap:PATH` or `synthetic[:N_FRAMES][:KEY=VALUE...]` (SYNTHETIC_SPEC); `every=N` plays every N-th frame
of it (the same camera moving N times faster: a fast-motion test case).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from octolog.kit import depthmodel
from octolog.kit.calibration import Calibration, is_calibration_file, load_calibration
from octolog.kit.depthmodel import DepthModel
from octolog.kit.errors import ConfigError, InputError
from octolog.kit.geometry import EncodedRgbd, RgbdFrame
from octolog.kit import metrics
from octolog.kit.mcaplog import damaged, read_wire, summarize
from octolog.kit.tum import open_tum, readout_for
from octolog.replay import depth_noise, source_gravity
from octolog.replay.standard import has_standard_frames, open_standard
from octolog.replay.synthetic import SyntheticScene
from octolog.schemas import codec, posemsgs, rgbdmsgs
from octolog.schemas.topics import (
    BACKEND_DEFERRED,
    KEYFRAME,
    KEYFRAME_COMPRESSED,
    RGBD,
    RGBD_COMPRESSED,
    TF_STATIC,
    TRACKING_STATUS,
)

T = TypeVar("T")
F = TypeVar("F", RgbdFrame, EncodedRgbd)


class Source(Protocol):
    name: str
    readout_s: float  # the colour camera's rolling-shutter readout time in s (0: global shutter or unknown)
    depth_model: DepthModel | None  # the depth camera's error model (kit/depthmodel.py); None: unknown
    encoded: bool  # it stores its images encoded (PNG/JPEG) and encoded_frames gives them undecoded

    def __len__(self) -> int: ...

    @property
    def duration_ns(self) -> int: ...

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]: ...

    def encoded_frames(self, start: int = 0, end: int | None = None) -> Iterator[EncodedRgbd]: ...

    def groundtruth_tum(self) -> str | None: ...

    def gravity_up(self) -> np.ndarray | None:
        """Up (unit vector) in the first frame's optical frame from the source's accelerometer;
        None without one (octolog.replay.source_gravity)."""
        ...


def _not_encoded(source: Source) -> Iterator[EncodedRgbd]:
    raise ConfigError(f"{source.name}: its frames are not stored encoded (replay.wire_compression=source "
                      "sends them raw)")


@dataclass
class TumSource:
    path: Path
    camera: str = ""  # freiburg1/2/3; "": the one the folder's name says (an error if it says none)
    every: int = 1  # every N-th pair only: the PNGs in between are never read
    calibration: Calibration | None = None  # the calibration file's (`camera` names one), else None

    def __post_init__(self) -> None:
        if is_calibration_file(self.camera):  # a camera the folder's name cannot say
            cal = load_calibration(self.camera)
            seq = open_tum(self.path, cal.intrinsics, camera=cal.name)
            seq = dataclasses.replace(seq, depth_scale_m=cal.depth_scale_m or seq.depth_scale_m)
            self.readout_s, self.depth_model = cal.readout_s, cal.depth_model
            self.calibration = cal
        else:
            seq = open_tum(self.path, camera=self.camera)
            self.readout_s = readout_for(seq.camera)  # the colour camera's rolling shutter (0 = unknown)
            self.depth_model = depthmodel.KINECT  # TUM's freiburg cameras: Kinect v1 / Xtion
        self.seq = seq if self.every == 1 else dataclasses.replace(seq, pairs=seq.pairs[:: self.every])
        self.name = f"tum:{self.path}" + (f" (every {self.every})" if self.every > 1 else "")

    def __len__(self) -> int:
        return len(self.seq)

    @property
    def duration_ns(self) -> int:
        return self.seq.duration_ns

    encoded = True  # PNG files

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
        return self.seq.frames(start, end)

    def encoded_frames(self, start: int = 0, end: int | None = None) -> Iterator[EncodedRgbd]:
        return self.seq.encoded_frames(start, end)

    def groundtruth_tum(self) -> str | None:
        return self.seq.groundtruth.read_text() if self.seq.groundtruth else None

    def gravity_up(self) -> np.ndarray | None:
        return source_gravity.tum_up(self.path, self.seq.pairs[0][0])


@dataclass
class McapSource:
    """RGB-D frames from an octolog MCAP (`/camera/rgbd` as `octolog_msgs/msg/RgbdFrame`).

    With `only_consumed`, just the frames the logged tracker consumed (its statuses say which).
    """

    path: Path
    only_consumed: bool = False
    calibration: str = ""  # a calibration file for a recording without CameraInfo (replay.camera)
    keyframes_only: bool = False  # a log fed to a mapper alone (replay.play = tracker): frames optional
    pair_ms: float = 20.0  # a recording's colour and depth images closer than this pair (replay.pair_ms)

    def __post_init__(self) -> None:
        self.name = f"mcap:{self.path}"
        self._calibration = load_calibration(self.calibration) if self.calibration else None
        summary = summarize(self.path)
        if not summary.complete:
            raise InputError(damaged(self.path, summary.problem))
        # a session log holds the frames raw or compressed (replay.wire_compression)
        wire = summary.wire_topics
        self._topic = RGBD_COMPRESSED if RGBD_COMPRESSED.name in wire else RGBD
        ts = wire.get(self._topic.name)
        self._standard = None
        if ts is None and self.keyframes_only:
            # a log kept where the camera was not (`octolog log --no-frames`): its keyframes suffice
            kfs = wire.get(KEYFRAME.name) or wire.get(KEYFRAME_COMPRESSED.name)
            if kfs is None:
                raise InputError(f"{self.path}: no /{KEYFRAME.name} topic: nothing to feed a mapper with")
            self._count, self._metadata, self._span = 0, summary.metadata, (kfs.first_ns, kfs.last_ns)
            self._consumed = None
            return
        if ts is None:
            if not has_standard_frames(summary.topics) and (KEYFRAME.name in wire or KEYFRAME_COMPRESSED.name in wire):
                raise InputError(f"{self.path}: a log without camera frames (`octolog log --no-frames`): "
                                 f"its keyframes replay into the mapper (`octolog replay SESSION --stages mapper`)")
            if not has_standard_frames(summary.topics):
                raise InputError(f"{self.path}: neither /{RGBD.name} nor colour + aligned depth topics "
                                 f"(topics: {', '.join(sorted(summary.topics)) or 'none'})")
            if self.only_consumed:
                raise InputError(f"{self.path}: a recording, not a session log: no record of consumed frames")
            # a recording or an import: colour and depth on their own topics, paired like TUM
            self._standard = open_standard(self.path, self._calibration, max_dt_ns=round(self.pair_ms * 1e6))
            self._count = len(self._standard)
            self._metadata = summary.metadata
            return
        if ts.msgtype != self._topic.msgtype:
            raise InputError(f"{self.path}: /{self._topic.name} holds {ts.msgtype}, want {self._topic.msgtype}")
        self._count = ts.count
        self._metadata = summary.metadata
        self._span = (ts.first_ns, ts.last_ns)
        self._consumed: set[int] | None = None
        if self.only_consumed:
            self._consumed = consumed_frames(self.path)
            self._count = len(self._consumed)

    def __len__(self) -> int:
        return self._count

    @property
    def readout_s(self) -> float:
        """The colour camera's rolling-shutter readout: an import's calibration record says it, a
        session log's tracker config used it; else 0 (the D455's colour camera has a global shutter)."""
        if self._calibration is not None:
            return self._calibration.readout_s
        calib = self._metadata.get("calibration", {})
        try:
            if "color_readout_s" in calib:
                return float(calib["color_readout_s"])
            tracker = json.loads(self._metadata.get("config", {}).get("tracker", "{}"))
            return float(tracker.get("rolling_shutter_ms") or 0.0) / 1e3
        except (ValueError, TypeError, AttributeError):
            raise InputError(f"{self.path}: unreadable colour readout time in the metadata") from None

    @property
    def depth_model(self) -> DepthModel | None:
        """The depth camera's error model: a calibration file's, the recording's `calibration` record's
        (kit/depthmodel.FIELDS), a RealSense's from its product name and its depth stream's focal length;
        else None."""
        if self._calibration is not None:
            return self._calibration.depth_model
        calib = self._metadata.get("calibration", {})
        try:
            given = depthmodel.from_fields(calib)
            if given is not None:
                return given
            depth = json.loads(calib.get("depth_intrinsics") or "{}")
        except ValueError as exc:
            raise InputError(f"{self.path}: calibration metadata: {exc}") from None
        name = str(self._metadata.get("device", {}).get("name", ""))
        return depthmodel.realsense(name, float(depth["fx"])) if "fx" in depth else None

    @property
    def duration_ns(self) -> int:
        if self._standard is not None:
            return self._standard.duration_ns
        return self._span[1] - self._span[0]

    @property
    def encoded(self) -> bool:
        """A session log whose frames travelled compressed: they replay as they were logged."""
        return self._standard is None and self._topic is RGBD_COMPRESSED

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
        if self._standard is not None:
            yield from self._standard.frames(start, end)
            return
        yield from self._logged(start, end, rgbdmsgs.rgbd_from_msg)

    def encoded_frames(self, start: int = 0, end: int | None = None) -> Iterator[EncodedRgbd]:
        if not self.encoded:
            yield from _not_encoded(self)
        yield from self._logged(start, end, rgbdmsgs.encoded_rgbd_from_msg)

    def _logged(self, start: int, end: int | None, convert: Callable[[Any], T]) -> Iterator[T]:
        i = 0
        topic = self._topic
        for n, m in enumerate(read_wire(self.path, [topic.name])):
            try:
                msg = codec.decode(m.data, topic.msgtype)
                if self._consumed is not None and int(msg.seq) not in self._consumed:
                    continue
                if start <= i and (end is None or i < end):
                    yield convert(msg)
            except InputError as exc:
                raise InputError(f"{self.path}: message {n} on /{topic.name}: {exc}") from None
            i += 1
            if end is not None and i >= end:
                return

    def groundtruth_tum(self) -> str | None:
        return self._metadata.get("groundtruth", {}).get("tum")

    def static_transforms(self) -> list[tuple[str, str, np.ndarray]]:
        """The camera's static frames as the file has them (/tf_static; `world`, which a mapper
        hangs under `map`, left out)."""
        return [tf for m in read_wire(self.path, [TF_STATIC.name])
                for tf in posemsgs.tf_transforms(codec.decode(m.data, TF_STATIC.msgtype)) if tf[1] != "world"]

    def gravity_up(self) -> np.ndarray | None:
        """A recording's accelerometer at its first frame; the up vector the session that wrote a
        session log found (its metadata), if any."""
        if self._standard is not None:
            return self._standard.gravity_up()
        return source_gravity.up_from_metadata(self._metadata, str(self.path))


def consumed_frames(path: Path) -> set[int]:
    """Sequence numbers of the frames a logged tracker processed (every status but SKIPPED)."""
    skipped = codec.msgtype(TRACKING_STATUS.msgtype).SKIPPED
    seqs = set()
    for m in read_wire(path, [TRACKING_STATUS.name]):
        st = codec.decode(m.data, TRACKING_STATUS.msgtype)
        if st.state != skipped:
            seqs.add(int(st.seq))
    if not seqs:
        raise InputError(f"{path}: no /{TRACKING_STATUS.name} messages: cannot tell which frames the tracker consumed")
    return seqs


def backend_deferred(path: Path) -> list[int]:
    """Frame numbers of the keyframes a logged live tracker inserted without waiting for its back end
    (tracker/backend_deferred), ascending; a replay defers at the same frames."""
    return sorted(int(json.loads(codec.decode(m.data, BACKEND_DEFERRED.msgtype).data)["seq"])
                  for m in read_wire(path, [BACKEND_DEFERRED.name]))


SYNTHETIC_SPEC = ("synthetic[:N][:tilt=DEG][:motion=loop|turns][:start=S][:reverse=1][:exposure=MS]"
                  "[:noise=none|kinect|d455][:bias=PX][:seed=S][:imu=HZ][:imunoise=X][:imurot=DEG][:imudt=MS]"
                  "[:blank=AT+SECONDS][:people=cross|stand|round|close[+...]]")


@dataclass
class SyntheticSource:
    n_frames: int = 150
    start_tilt_deg: float = 0.0  # `tilt=DEG`: the camera starts looking down DEG more
    motion: str = "loop"  # `motion=turns`: the walk with fast head turns (150-210 deg/s)
    path_start_s: float = 0.0  # `start=S`: the walk starts S s along its path
    reverse: bool = False  # `reverse=1`: the walk goes the other way round
    exposure_ms: float = 0.0  # `exposure=MS`: colour blurred by the camera's rotation over MS
    depth_noise: str = "none"  # `noise=kinect|d455`: the depth that sensor would read
    depth_bias_px: float = 0.0  # `bias=PX`: the depth sensor's systematic disparity offset (reads short if > 0)
    seed: int = 0  # `seed=S`: another room's textures and another draw of the depth noise
    imu_hz: float = 0.0  # `imu=HZ`: a simulated D455 IMU at HZ (replay/synthetic_imu.py)
    imu_noise_scale: float = 1.0  # `imunoise=X`: its noise X times the datasheet's (the tracker is not told)
    imu_rotation_deg: float = 0.0  # `imurot=DEG`: its axes turned DEG from the camera's (the tracker is not told)
    imu_late_ms: float = 0.0  # `imudt=MS`: its clock MS late (the tracker is not told)
    blank: tuple[float, float] = (0.0, 0.0)  # `blank=AT+S`: no texture in sight from AT s for S s
    people: str = ""  # `people=cross+stand`: people walking through the room (replay/synthetic_people.py)
    readout_s = 0.0  # rendered, every row at once
    encoded = False  # rendered pixels

    @property
    def depth_model(self) -> DepthModel | None:
        """The simulated sensor's (replay/depth_noise.py); None for exact depth."""
        s = depth_noise.SENSORS.get(self.depth_noise)
        return DepthModel(s.baseline_m, s.focal_px, s.sigma_px) if s is not None else None

    def __post_init__(self) -> None:
        self.scene = SyntheticScene(n_frames=self.n_frames, start_tilt_deg=self.start_tilt_deg, motion=self.motion,
                                    path_start_s=self.path_start_s, reverse=self.reverse, exposure_ms=self.exposure_ms, depth_noise=self.depth_noise,
                                    depth_bias_px=self.depth_bias_px, seed=self.seed, imu_hz=self.imu_hz,
                                    imu_noise_scale=self.imu_noise_scale, imu_rotation_deg=self.imu_rotation_deg,
                                    imu_late_ms=self.imu_late_ms,
                                    blank_at_s=self.blank[0], blank_s=self.blank[1], people=self.people)
        options = {"tilt": f"{self.start_tilt_deg:g}" if self.start_tilt_deg else "",
                   "motion": "" if self.motion == "loop" else self.motion,
                   "start": f"{self.path_start_s:g}" if self.path_start_s else "",
                   "reverse": "1" if self.reverse else "",
                   "exposure": f"{self.exposure_ms:g}" if self.exposure_ms else "",
                   "noise": "" if self.depth_noise == "none" else self.depth_noise,
                   "bias": f"{self.depth_bias_px:g}" if self.depth_bias_px else "",
                   "seed": str(self.seed) if self.seed else "", "imu": f"{self.imu_hz:g}" if self.imu_hz else "",
                   "imunoise": f"{self.imu_noise_scale:g}" if self.imu_noise_scale != 1.0 else "",
                   "imurot": f"{self.imu_rotation_deg:g}" if self.imu_rotation_deg else "",
                   "imudt": f"{self.imu_late_ms:g}" if self.imu_late_ms else "",
                   "blank": "{:g}+{:g}".format(*self.blank) if self.blank[1] else "", "people": self.people}
        self.name = ":".join([f"synthetic:{self.n_frames}", *(f"{k}={v}" for k, v in options.items() if v)])

    def gravity_up(self) -> np.ndarray | None:
        return self.scene.gravity_up()

    def __len__(self) -> int:
        return self.n_frames

    @property
    def duration_ns(self) -> int:
        return self.scene.stamp_ns(self.n_frames - 1) - self.scene.stamp_ns(0)

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
        for i in range(start, self.n_frames if end is None else min(end, self.n_frames)):
            yield self.scene.render(i)

    def encoded_frames(self, start: int = 0, end: int | None = None) -> Iterator[EncodedRgbd]:
        return _not_encoded(self)

    def groundtruth_tum(self) -> str | None:
        return self.scene.groundtruth_tum()


@dataclass
class Subsampled:
    """Every `every`-th frame of `inner`, numbered 0, 1, 2, ... with the source's stamps: the same
    camera moving `every` times faster, at 1/`every` of the frame rate."""

    inner: Source
    every: int

    def __post_init__(self) -> None:
        self.name = f"{self.inner.name} (every {self.every})"
        self.readout_s, self.depth_model = self.inner.readout_s, self.inner.depth_model
        self.encoded = self.inner.encoded

    def __len__(self) -> int:
        return -(-len(self.inner) // self.every)

    @property
    def duration_ns(self) -> int:
        return self.inner.duration_ns

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
        if isinstance(self.inner, SyntheticSource):  # it renders any frame alone: those between are never rendered
            stop = len(self.inner) if end is None else min(end * self.every, len(self.inner))
            return (dataclasses.replace(self.inner.scene.render(i), seq=i // self.every)
                    for i in range(start * self.every, stop, self.every))
        return self._every(self.inner.frames, start, end)

    def encoded_frames(self, start: int = 0, end: int | None = None) -> Iterator[EncodedRgbd]:
        return self._every(self.inner.encoded_frames, start, end)

    def _every(self, frames: Callable[[int, int | None], Iterator[F]], start: int, end: int | None) -> Iterator[F]:
        stop = None if end is None else end * self.every
        for i, frame in enumerate(frames(start * self.every, stop)):
            if i % self.every == 0:
                yield dataclasses.replace(frame, seq=start + i // self.every)

    def groundtruth_tum(self) -> str | None:
        return self.inner.groundtruth_tum()

    def gravity_up(self) -> np.ndarray | None:
        return self.inner.gravity_up()  # the same first frame


@dataclass
class Retimed:
    """`inner` (every `factor`-th frame of a source) stamped `factor` times closer together: sensor
    time t becomes t0 + (t - t0) / factor for the frames and the ground truth alike, so every N-th
    frame plays at the source's own frame rate: the same camera moving N times faster at the same
    frame rate (replay.retime). t0 is the first frame's stamp."""

    inner: Source
    factor: int

    def __post_init__(self) -> None:
        self.name = f"{self.inner.name} at {self.factor}x speed"
        self.readout_s, self.depth_model = self.inner.readout_s, self.inner.depth_model
        self.encoded = self.inner.encoded
        first = self.inner.encoded_frames(0, 1) if self.encoded else self.inner.frames(0, 1)
        self.t0_ns = next(iter(first)).stamp_ns

    def _ns(self, ns: int) -> int:
        return self.t0_ns + round((ns - self.t0_ns) / self.factor)

    def __len__(self) -> int:
        return len(self.inner)

    @property
    def duration_ns(self) -> int:
        return round(self.inner.duration_ns / self.factor)

    def frames(self, start: int = 0, end: int | None = None) -> Iterator[RgbdFrame]:
        return (dataclasses.replace(f, stamp_ns=self._ns(f.stamp_ns)) for f in self.inner.frames(start, end))

    def encoded_frames(self, start: int = 0, end: int | None = None) -> Iterator[EncodedRgbd]:
        return (dataclasses.replace(f, stamp_ns=self._ns(f.stamp_ns)) for f in self.inner.encoded_frames(start, end))

    def groundtruth_tum(self) -> str | None:
        text = self.inner.groundtruth_tum()
        if text is None:
            return None
        truth = metrics.parse_tum(text, "ground truth")
        return metrics.format_tum(np.array([self._ns(int(t)) for t in truth.stamps_ns]), truth)

    def gravity_up(self) -> np.ndarray | None:
        return self.inner.gravity_up()


def open_source(spec: str, *, only_consumed: bool = False, camera: str = "", every: int = 1,
                keyframes_only: bool = False, retime: bool = False, pair_ms: float = 20.0) -> Source:
    """Open `tum:PATH`, `mcap:PATH` or `synthetic[:N][:KEY=VALUE...]` (SYNTHETIC_SPEC); errors name the
    problem in one line.
    `camera` names a TUM folder's camera when its name does not (replay.camera); `every` > 1 plays
    every `every`-th frame only (replay.every), with `retime` at the source's own frame rate (replay.retime)."""
    if every < 1:
        raise ConfigError(f"replay.every {every}: want >= 1")
    kind, _, arg = spec.partition(":")
    if keyframes_only and kind == "mcap" and arg:
        return McapSource(Path(arg), keyframes_only=True)
    if kind == "tum" and arg:
        source: Source = TumSource(Path(arg), camera, every)
    else:
        source = _open(spec, only_consumed, camera, pair_ms)
        source = source if every == 1 else Subsampled(source, every)
    return Retimed(source, every) if retime and every > 1 else source


def _open(spec: str, only_consumed: bool, camera: str, pair_ms: float = 20.0) -> Source:
    kind, _, arg = spec.partition(":")
    if camera and kind != "tum" and not (kind == "mcap" and is_calibration_file(camera)):
        raise ConfigError(f"replay.camera {camera!r}: a tum: source takes a camera name or a calibration file, "
                          f"an mcap: recording a calibration file (got {spec!r})")
    if kind == "mcap" and arg:
        return McapSource(Path(arg), only_consumed, camera, pair_ms=pair_ms)
    if only_consumed:
        raise ConfigError(f"source {spec!r}: only an MCAP session log knows which frames were consumed")
    if kind == "synthetic":
        return _synthetic(spec, arg)
    raise ConfigError(f"source {spec!r}: want tum:PATH, mcap:PATH or {SYNTHETIC_SPEC}")


def _synthetic(spec: str, arg: str) -> SyntheticSource:
    """`synthetic[:N][:KEY=VALUE...]` (SYNTHETIC_SPEC); a bad count, key or value is a one-line error."""
    count, *options = arg.split(":") if arg else [""]
    keys = {"tilt": "start_tilt_deg", "motion": "motion", "start": "path_start_s", "reverse": "reverse",
            "exposure": "exposure_ms", "noise": "depth_noise",
            "bias": "depth_bias_px", "seed": "seed", "imu": "imu_hz", "imunoise": "imu_noise_scale",
            "imurot": "imu_rotation_deg", "imudt": "imu_late_ms", "blank": "blank", "people": "people"}
    kwargs: dict[str, Any] = {}
    try:
        n = int(count) if count else 150
        for option in options:
            key, eq, value = option.partition("=")
            if not eq or key not in keys or keys[key] in kwargs:
                raise ValueError(option)
            if key == "reverse" and value not in ("0", "1"):
                raise ValueError(option)
            kwargs[keys[key]] = (value if key in ("motion", "noise", "people") else int(value) if key == "seed" else
                                 value == "1" if key == "reverse" else
                                 tuple(float(v) for v in value.split("+", 1)) if key == "blank" else float(value))
            if key == "blank" and len(kwargs["blank"]) != 2:
                raise ValueError(option)
        source = SyntheticSource(n, **kwargs)
    except ValueError:
        raise ConfigError(f"source {spec!r}: want {SYNTHETIC_SPEC}") from None
    if n < 2:
        raise ConfigError(f"source {spec!r}: want at least 2 frames")
    if not -80.0 <= source.start_tilt_deg <= 80.0:
        raise ConfigError(f"source {spec!r}: want {SYNTHETIC_SPEC} with -80 <= DEG <= 80")
    return source
