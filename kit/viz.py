"""Rerun logging: the only module that imports rerun.

`--rerun off` (default), `--rerun save:DIR` (one `<stage>.rrd` per stage) or `--rerun connect:URL`
(stream to a viewer; with `$OCTOLOG_RERUN_COPY` set, as `octolog run` sets it to OUT/rerun, also
saved there, so a viewer that is not there costs nothing). A viewer that cannot be reached is a
warning, never a stage's failure: `VIEWER_MISSED` says so for the stage's report. All stages of a
session share one recording id so their data merges into one recording; timelines are `sensor_time`
(sensor timestamps) and `frame` (source sequence numbers). Entity paths mirror topic names.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from octolog.kit.cpuclock import charge, note_threads
from octolog.kit.errors import ConfigError, DiskFull, VizError
from octolog.kit.geometry import Intrinsics, matrix_to_pose
from octolog.schemas.imagecodec import depth_png

APPLICATION_ID = "octolog"
COPY_ENV = "OCTOLOG_RERUN_COPY"  # with `connect`: also save the stage's recording in this folder
DEFAULT_VIEWER = "rerun+http://127.0.0.1:9876/proxy"  # rerun's own default for `connect` without a URL
# {"url": ..., "saved": path or None, "reason": ...} once this process's viewer could not be reached
VIEWER_MISSED: dict[str, str | None] = {}

log = logging.getLogger(__name__)


JPEG_QUALITY = 75  # colour in the recordings: for looking at, not for measuring
Colours = np.ndarray | Sequence[int]  # one RGB(A) for all, or one per item
Encoded = np.ndarray | bytes | bytearray | memoryview  # an image file's bytes


def cv2() -> ModuleType:
    import cv2 as module  # here: only a stage that logs images needs OpenCV's codecs

    return module


def _encode(image: np.ndarray, ext: str, params: list[int]) -> np.ndarray:
    ok, buf = cv2().imencode(ext, image, params)
    if not ok:
        raise VizError(f"rerun: cannot encode a {image.shape} {image.dtype} image as {ext}")
    return buf.reshape(-1)


def encode_jpeg(rgb: np.ndarray) -> np.ndarray:
    """An RGB image as the JPEG the recordings hold (thread-safe: a stage may encode ahead, off its loop)."""
    cv = cv2()
    with charge("rerun"):
        return _encode(cv.cvtColor(rgb, cv.COLOR_RGB2BGR), ".jpg", [cv.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])


def _blob(data: Encoded) -> np.ndarray:
    return np.frombuffer(data, dtype=np.uint8) if isinstance(data, bytes | bytearray | memoryview) else \
        np.asarray(data, dtype=np.uint8).reshape(-1)


PIPELINE_STAGES = ("replay", "tracker", "mapper")


def pipeline_blueprint() -> Any:  # Any: rerun is imported only when used (1.5 s)
    """The viewer's layout for a session: the map in 3D, the camera and the keyframe depth, the grid,
    the tracker's and mapper's timings and the events; fixed, so every launch looks the same."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            # rooted at the map frame (z up): the mapper's cloud and voxels are logged in it (`map/...`)
            # and it places the tracker's `world` in it, so the room stands upright
            rrb.Spatial3DView(origin="/", contents=["/map/**", "/world/**"], name="map, trajectory and camera"),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/tracker/camera", name="camera and keypoints"),
                rrb.Spatial2DView(origin="world/tracker/keyframe", name="last keyframe's depth"),
                rrb.Spatial2DView(origin="mapper/grid", name="occupancy grid"),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="tracker/ms", name="tracker ms per frame"),
                rrb.TimeSeriesView(origin="tracker/inliers", name="tracker inliers"),
                rrb.TimeSeriesView(origin="mapper/ms", name="mapper ms per keyframe"),
                rrb.TextLogView(origin="/", contents=["tracker/events", "replay/events"], name="events"),
            ),
            column_shares=[3, 2, 2],
        ),
        collapse_panels=True,
    )


def parse_spec(spec: str) -> tuple[str, str]:
    """Split `off`, `save:DIR` or `connect[:URL]` into (kind, target)."""
    kind, _, target = spec.partition(":")
    if kind == "off" and not target:
        return "off", ""
    if kind == "save" and target:
        return "save", target
    if kind == "connect":
        return "connect", target
    raise ConfigError(f"--rerun {spec!r}: want off, save:DIR or connect[:URL]")


def viewer_unreachable(url: str, timeout_s: float = 1.0) -> str | None:
    """Why nothing would take a recording streamed to the viewer at `url` (`connect`'s target, or
    DEFAULT_VIEWER): nothing listens at its host and port, or they do not resolve; None when a
    TCP connection opens (the viewer, or whatever else listens there)."""
    parts = urlsplit(url.replace("rerun+", "", 1) if url.startswith("rerun+") else url)
    try:
        port = parts.port or {"https": 443, "http": 80}.get(parts.scheme, 9876)
    except ValueError:
        return f"{url} names no port"
    if not parts.hostname:
        return f"{url} names no host"
    try:
        with socket.create_connection((parts.hostname, port), timeout=timeout_s):
            return None
    except OSError as exc:
        return f"nothing listens at {parts.hostname}:{port} ({exc.strerror or exc})"


FILE_FLUSH_S = 1.0  # see Viz.__init__
# Streaming to a viewer, the last flush waits at most this long: rerun's gRPC sink waits for ever on a
# viewer it never reached (a saved copy, rerun's file sink beside it, is whole all the same)
VIEWER_FLUSH_S = 10.0


class Viz:
    """One stage's Rerun stream; every method is a no-op when disabled."""

    def __init__(self, spec: str, stage: str, recording_id: str) -> None:
        self.kind, target = parse_spec(spec)
        self.stage = stage
        self.rec: Any = None  # rerun's RecordingStream when on (Any: rerun is imported only then)
        self.path: Path | None = None
        self.viewer = (target or DEFAULT_VIEWER) if self.kind == "connect" else ""
        if self.kind == "off":
            return
        import rerun as rr  # here, not at the top: rerun-sdk takes ~1.5 s to import; "off" never needs it

        _arrow_without_pandas()
        self._rr = rr
        # Saved to a file, the rows of each entity are batched into a chunk a second, not Rerun's
        # 200 ms: the .rrd's footer (its chunk manifest, which lets the viewer open a recording
        # larger than memory) is kept in memory until the file closes, per chunk, which made the
        # tracker grow 10-13 MB a minute at 30 fps; a second halves that (docs/results.md) and the
        # file is 4 % smaller. A viewer that reads the file as it grows sees it up to a second late;
        # a connected viewer keeps the default.
        batching = rr.ChunkBatcherConfig(flush_tick=FILE_FLUSH_S) if self.kind == "save" else None
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id, batcher_config=batching)
        copy = os.environ.get(COPY_ENV) if self.kind == "connect" else None
        if self.kind == "save" or copy:
            self.path = Path(target if self.kind == "save" else copy) / f"{stage}.rrd"
            self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.kind == "save":
            self.rec.save(self.path)
        elif self.path is not None:  # the viewer and the file alike (rerun's tee of sinks)
            self.rec.set_sinks(rr.GrpcSink(self.viewer), rr.FileSink(self.path))
        else:
            self.rec.connect_grpc(self.viewer)
        # the root is the map frame (REP 103: x forward, y left, z up); `world` (the tracker's: its
        # first camera's optical frame) sits in it by the transform the mapper logs (`map_frame`)
        self.rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if stage in PIPELINE_STAGES:
            self.rec.send_blueprint(pipeline_blueprint())  # the same layout whichever stage's file opens first
        _warm_up(rr)

    @property
    def enabled(self) -> bool:
        return self.rec is not None

    def close(self) -> None:
        """Flush and close; a recording that could not be written raises DiskFull or VizError."""
        if self.rec is None:
            return
        rec, self.rec = self.rec, None
        try:
            with charge("rerun"):
                rec.flush(timeout_sec=VIEWER_FLUSH_S if self.kind == "connect" else 1e38)
        except RuntimeError as exc:  # rerun's file writer died (it logs the OS error itself), or no viewer
            if self.kind != "connect":
                raise self._write_error(exc) from None
            self._viewer_missed(exc)
        finally:
            note_threads()  # rerun's threads end with the recording: their CPU, counted before
            rec.disconnect()  # a viewer never reached: rerun gives it one last try (~5 s)

    def _viewer_missed(self, exc: RuntimeError) -> None:
        """The viewer was not there: said once, the run goes on (its file, if any, is whole)."""
        saved = str(self.path) if self.path is not None else None
        VIEWER_MISSED.update(url=self.viewer, saved=saved, reason=str(exc).splitlines()[0] if str(exc) else "")
        log.warning("rerun: the viewer at %s could not be reached (%s); %s", self.viewer, VIEWER_MISSED["reason"],
                    f"the recording is saved in {saved}" if saved else "nothing of this stage's recording was kept")

    def _write_error(self, exc: RuntimeError) -> Exception:
        if self.path is None:
            return VizError(f"rerun: cannot send the recording: {exc}")
        try:
            full = shutil.disk_usage(self.path.parent).free < 1024 * 1024
        except OSError:
            full = False
        if full:
            return DiskFull(f"disk full: {self.path} (no space left on the disk holding {self.path.parent})")
        return VizError(f"{self.path}: rerun could not write the recording ({exc})")

    def __enter__(self) -> Viz:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- time ------------------------------------------------------------------------------

    def set_time(self, stamp_ns: int, frame: int | None = None) -> None:
        if self.rec is None:
            return
        self.rec.set_time("sensor_time", timestamp=np.datetime64(stamp_ns, "ns"))
        if frame is not None:
            self.rec.set_time("frame", sequence=frame)

    # --- archetypes ------------------------------------------------------------------------

    def camera(self, path: str, intr: Intrinsics, *, static: bool = True) -> None:
        if self.rec is None:
            return
        rr = self._rr
        self.rec.log(path, rr.Pinhole(image_from_camera=intr.matrix, resolution=[intr.width, intr.height],
                                      camera_xyz=rr.ViewCoordinates.RDF), static=static)

    def map_frame(self, map_from_world: np.ndarray) -> None:
        """Place `world` in the z-up root: the map frame the grid lies in (gravity-aligned when the
        source has an accelerometer, else from a level first camera)."""
        if self.rec is None:
            return
        T = np.asarray(map_from_world, dtype=np.float64)
        self.rec.log("world", self._rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)

    def pose(self, path: str, world_from_camera: np.ndarray) -> None:
        if self.rec is None:
            return
        t, q = matrix_to_pose(world_from_camera)
        self.rec.log(path, self._rr.Transform3D(translation=t, quaternion=q))

    def rgb(self, path: str, image: np.ndarray, jpeg: Encoded | None = None) -> None:
        """A colour image, logged as JPEG (`jpeg`: the bytes the frame came with, else encoded here):
        a tenth of the raw size in the .rrd, and the viewer decodes it."""
        if self.rec is None:
            return
        if jpeg is None:
            jpeg = encode_jpeg(image)
        # as a uint8 array: rerun converts `bytes` byte by byte (7 ms a frame), an array in 0.1 ms
        self.rec.log(path, self._rr.EncodedImage(contents=_blob(jpeg), media_type="image/jpeg"))

    def depth(self, path: str, depth: np.ndarray, depth_scale_m: float, png: Encoded | None = None) -> None:
        """A 16-bit depth image, logged as lossless PNG (`png`: the bytes it came with, else encoded here)."""
        if self.rec is None:
            return
        if png is None:
            png = depth_png(depth)
        self.rec.log(path, self._rr.EncodedDepthImage(blob=_blob(png), media_type="image/png",
                                                      meter=1.0 / depth_scale_m))

    def image(self, path: str, image: np.ndarray) -> None:
        if self.rec is not None:
            self.rec.log(path, self._rr.Image(image))


    def points2d(self, path: str, xy: np.ndarray, colors: Colours | None = None) -> None:
        if self.rec is not None:
            self.rec.log(path, self._rr.Points2D(xy, colors=colors, radii=2.0))

    def points3d(self, path: str, xyz: np.ndarray, colors: Colours | None = None, *, radius: float = 0.005,
                 static: bool = False) -> None:
        if self.rec is not None:
            self.rec.log(path, self._rr.Points3D(xyz, colors=colors, radii=radius), static=static)

    def boxes(self, path: str, centers: np.ndarray, size_m: float, colors: Colours | None = None, *,
              static: bool = False) -> None:
        if self.rec is not None:
            half = np.full((len(centers), 3), size_m / 2, dtype=np.float32)
            self.rec.log(path, self._rr.Boxes3D(centers=centers, half_sizes=half, colors=colors,
                                                fill_mode="solid"), static=static)

    def path3d(self, path: str, xyz: np.ndarray, color: Colours | None = None) -> None:
        if self.rec is not None and len(xyz) > 1:
            self.rec.log(path, self._rr.LineStrips3D([xyz], colors=color))

    def scalar(self, path: str, value: float) -> None:
        if self.rec is not None:
            self.rec.log(path, self._rr.Scalars(value))

    def text(self, path: str, text: str) -> None:
        if self.rec is not None:
            self.rec.log(path, self._rr.TextLog(text))


class _NoPandas:
    """A meta path finder that refuses pandas (see `_arrow_without_pandas`)."""

    @staticmethod
    def find_spec(name: str, path: object = None, target: object = None) -> None:
        if name.partition(".")[0] == "pandas":
            raise ImportError("pandas: not for pyarrow in a stage (kit/viz.py)")


def _arrow_without_pandas() -> None:
    """Rerun converts what it logs with pyarrow, whose first conversion imports pandas to tell
    DataFrames apart (0.15 s of CPU in every stage that logs, for a type no stage logs). That one
    look is made here with pandas refused: pyarrow then takes pandas as absent for good, and pandas
    stays importable for everything else (evo)."""
    if "pandas" in sys.modules:
        return  # imported already: pyarrow's look costs nothing
    import pyarrow as pa

    sys.meta_path.insert(0, _NoPandas)  # type: ignore[arg-type]
    try:
        pa.array(np.zeros(1, np.uint8))
    finally:
        sys.meta_path.remove(_NoPandas)  # type: ignore[arg-type]


def _warm_up(rr: ModuleType) -> None:
    """One of each archetype the stages log, built and dropped: Rerun sets up a type's Arrow
    conversion on its first use (120 ms for these here, holding the GIL), which then happens before
    the stream, not on a live tracker's first frames."""
    z3, c3 = np.zeros((2, 3), np.float32), np.zeros((2, 3), np.uint8)
    rr.Transform3D(translation=[0.0, 0.0, 0.0], quaternion=[0.0, 0.0, 0.0, 1.0])
    rr.Transform3D(translation=[0.0, 0.0, 0.0], mat3x3=np.eye(3))
    rr.Pinhole(image_from_camera=np.eye(3), resolution=[8, 8], camera_xyz=rr.ViewCoordinates.RDF)
    rr.EncodedImage(contents=np.zeros(2, np.uint8), media_type="image/jpeg")
    rr.EncodedDepthImage(blob=np.zeros(2, np.uint8), media_type="image/png", meter=1000.0)
    rr.Image(np.zeros((2, 2, 3), np.uint8))
    rr.Points2D(z3[:, :2], colors=c3, radii=2.0)
    rr.Points3D(z3, colors=c3, radii=0.005)
    rr.Boxes3D(centers=z3, half_sizes=z3, colors=c3, fill_mode="solid")
    rr.LineStrips3D([z3], colors=[0, 0, 0])
    rr.Scalars(0.0)
    rr.TextLog("")
