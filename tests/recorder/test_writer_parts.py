"""Each part of the recorder's writer (recorder/writer.py: Recorder composes them) built and checked
alone: the capture queue and its drop counts, the encoding of a capture, the split MCAP output."""

from __future__ import annotations

import errno
import json
import os
import threading
import time

import numpy as np
import pytest

from octolog.kit import recordfile
from octolog.kit.errors import DiskFull, RecorderError
from octolog.kit.geometry import Intrinsics
from octolog.kit.mcaplog import read_messages, summarize
from octolog.recorder.capture import Capture, DeviceDescription, MotionSample, VideoFrame
from octolog.recorder.capture_encoding import encode_capture, tf_static
from octolog.recorder.capture_queue import MOTION_BATCH, CaptureQueue
from octolog.recorder.recording_types import (
    PNG_FORMAT,
    STREAMS,
    Encoding,
    StreamStats,
    camera_transforms,
    frame_names,
)
from octolog.recorder.split_output import RecordingProgress, SplitMcapOutput
from octolog.schemas import codec, imagecodec, posemsgs, sensormsgs
from octolog.schemas import topics as T

COLOR = Intrinsics(64, 48, 50.0, 51.0, 32.0, 24.0, (0.1, 0.0, 0.0, 0.0, 0.0))
DEPTH = Intrinsics(40, 30, 30.0, 30.0, 20.0, 15.0)
FRAMES = frame_names("camera")
MS = 1_000_000


def _device() -> DeviceDescription:
    return DeviceDescription("D455 test", "123", "5.0", "test", color=COLOR, depth=DEPTH, gyro_fps=200, accel_fps=100,
                             depth_from_gyro=np.eye(4), depth_from_accel=np.eye(4))


def _frame(i: int, *, stamp_ns: int | None = None, size: tuple[int, int] = (48, 64)) -> Capture:
    """A colour + aligned depth pair, frame number i, seen as such."""
    rng = np.random.default_rng(i)
    t = stamp_ns if stamp_ns is not None else 1_000 * MS + i * 33 * MS
    rgb = rng.integers(0, 255, (*size, 3), dtype=np.uint8)
    depth = rng.integers(0, 5000, size, dtype=np.uint16)
    return Capture(color=VideoFrame("color", i, t, rgb), aligned_depth=VideoFrame("aligned_depth", i, t, depth),
                   seen=[("color", i), ("depth", i)])


def _imu(i: int) -> Capture:
    return Capture(motion=[MotionSample("gyro", i, 1_000 * MS + i * 5 * MS, (0.1 * i, 0.0, -1.0))],
                   seen=[("gyro", i)])


# --- CaptureQueue -----------------------------------------------------------------------------------


def test_queue_counts_device_gaps_and_unpaired_depth():
    q = CaptureQueue(8, block_when_full=False)
    for fn in (0, 1, 4, 5, 9):
        q.submit(Capture(seen=[("color", fn)], unpaired=["aligned_depth"] if fn == 4 else []))
    assert q.stats["color"].device_gaps == 5 and q.stats["color"].last_frame_number == 9
    assert q.stats["aligned_depth"].unpaired == 1 and q.stats["aligned_depth"].dropped == 1
    assert q.qsize() == 0  # nothing recordable: captures without samples only account


def test_queue_batches_imu_samples_into_the_next_frame():
    q = CaptureQueue(8, block_when_full=False)
    for i in range(5):
        q.submit(_imu(i))
    assert q.qsize() == 0  # IMU alone does not take a queue slot
    q.submit(_frame(0))
    cap = q.take(0.1)
    assert cap is not None and cap.color is not None
    assert [m.frame_number for m in cap.motion] == [0, 1, 2, 3, 4]
    for i in range(MOTION_BATCH):  # a full batch goes on its own
        q.submit(_imu(10 + i))
    cap = q.take(0.1)
    assert cap is not None and cap.color is None and len(cap.motion) == MOTION_BATCH
    q.submit(_imu(99))
    q.end()  # the batch left over, then the end
    last = q.take(0.1)
    assert last is not None and [m.frame_number for m in last.motion] == [99]
    assert not q.ended and q.take(0.1) is None and q.ended


def test_full_queue_drops_and_counts_per_stream():
    q = CaptureQueue(2, block_when_full=False)
    for i in range(5):
        q.submit(_frame(i))
    assert q.qsize() == 2
    assert q.stats["color"].queue_drops == 3 == q.stats["aligned_depth"].queue_drops
    assert q.stats["depth"].queue_drops == 0  # seen but not recorded in these captures: nothing to drop


def test_blocking_queue_waits_then_counts_unwritten_after_a_failure():
    q = CaptureQueue(1, block_when_full=True)
    q.submit(_frame(0))
    threading.Timer(0.3, q.fail).start()
    t0 = time.monotonic()
    q.submit(_frame(1))  # waits for room until the writer fails
    assert time.monotonic() - t0 >= 0.25
    assert q.stats["color"].unwritten == 1 and q.stats["color"].queue_drops == 0
    q.submit(_frame(2))  # failed: counted at once
    assert q.stats["color"].unwritten == 2
    q.drain_unwritten()  # what was queued before the failure
    assert q.stats["color"].unwritten == 3 and q.qsize() == 0 and not q.ended


def test_take_times_out_empty():
    q = CaptureQueue(2, block_when_full=False)
    t0 = time.monotonic()
    assert q.take(0.05) is None and not q.ended and time.monotonic() - t0 >= 0.04


# --- encode_capture ---------------------------------------------------------------------------------


def test_encoding_raw_is_exact_and_in_write_order():
    device = _device()
    cap = _frame(3)
    cap.depth = VideoFrame("depth", 3, cap.stamp_ns + 1, np.arange(1200, dtype=np.uint16).reshape(30, 40))
    cap.motion = _imu(7).motion + [MotionSample("accel", 2, 1_040 * MS, (0.0, -9.8, 0.5))]
    msgs = encode_capture(cap, device, FRAMES, Encoding(color_codec="raw", depth_codec="raw"))
    assert [m.topic for m in msgs] == [T.COLOR, T.COLOR_INFO, T.ALIGNED_DEPTH, T.ALIGNED_DEPTH_INFO, T.DEPTH,
                                       T.DEPTH_INFO, T.GYRO, T.ACCEL]
    color = codec.decode(msgs[0].data, T.COLOR.msgtype)
    assert np.array_equal(sensormsgs.image_array(color), cap.color.array)
    assert color.header.frame_id == "camera_color_optical_frame" and codec.stamp_ns(color.header) == cap.stamp_ns
    assert sensormsgs.intrinsics_from(codec.decode(msgs[1].data, T.COLOR_INFO.msgtype)) == COLOR
    aligned_info = sensormsgs.intrinsics_from(codec.decode(msgs[3].data, T.ALIGNED_DEPTH_INFO.msgtype))
    depth_info = codec.decode(msgs[5].data, T.DEPTH_INFO.msgtype)
    assert aligned_info.fx == COLOR.fx  # aligned depth is in the colour camera
    assert sensormsgs.intrinsics_from(depth_info).fx == DEPTH.fx and depth_info.header.frame_id == FRAMES["depth"]
    raw = codec.decode(msgs[4].data, T.DEPTH.msgtype)
    assert np.array_equal(sensormsgs.image_array(raw), cap.depth.array) and msgs[4].stamp_ns == cap.stamp_ns + 1
    accel = codec.decode(msgs[7].data, T.ACCEL.msgtype)
    assert accel.header.frame_id == FRAMES["accel"]
    assert (accel.linear_acceleration.y, accel.linear_acceleration.z) == pytest.approx((-9.8, 0.5))


def test_encoding_png_depth_is_lossless_and_jpeg_colour_close():
    cap = _frame(1)
    msgs = encode_capture(cap, _device(), FRAMES, Encoding(color_codec="jpeg", depth_codec="png", png_level=3))
    assert [m.topic for m in msgs] == [T.COLOR_JPEG, T.COLOR_INFO, T.ALIGNED_DEPTH_PNG, T.ALIGNED_DEPTH_INFO]
    png = codec.decode(msgs[2].data, T.ALIGNED_DEPTH_PNG.msgtype)
    assert png.format == PNG_FORMAT
    assert np.array_equal(imagecodec.compressed_image_array(png), cap.aligned_depth.array)
    jpeg = imagecodec.compressed_image_array(codec.decode(msgs[0].data, T.COLOR_JPEG.msgtype))
    assert jpeg.shape == cap.color.array.shape
    # a pure function: the same capture gives the same bytes
    assert msgs == encode_capture(cap, _device(), FRAMES, Encoding(color_codec="jpeg", depth_codec="png", png_level=3))


# --- SplitMcapOutput ---------------------------------------------------------------------------------


class _Progress:
    """Stands in for the Recorder's view of the whole recording."""

    def __init__(self) -> None:
        self.stop_reason = ""
        self.streams = {s: StreamStats() for s in STREAMS}
        self.calls = 0

    def __call__(self) -> RecordingProgress:
        self.calls += 1
        return RecordingProgress(self.stop_reason, self.streams, 7, 123, 1.5)


def _output(tmp_path, progress, *, split_size: int = 0, split_ns: int = 0, min_free: int = 0, chunk_size: int = 1 << 20,
            name: str = "out"):
    device = _device()
    meta = {**device.metadata(), "config": {"recorder": "{}"}}
    return SplitMcapOutput(lambda i: tmp_path / f"{name}_{i:04d}.mcap", compression="lz4", chunk_size=chunk_size,
                           split_size=split_size, split_ns=split_ns, min_free=min_free, metadata=meta,
                           transforms=camera_transforms(device, FRAMES), progress=progress)


def _write(out: SplitMcapOutput, cap: Capture, enc: Encoding = Encoding()) -> None:
    out.write(encode_capture(cap, _device(), FRAMES, enc), cap.stamp_ns,
              may_split=cap.color is not None or cap.aligned_depth is not None)


def test_output_splits_by_sensor_time_at_frames_only(tmp_path):
    progress = _Progress()
    out = _output(tmp_path, progress, split_ns=100 * MS)
    assert out.files == 0 and out.path is None
    for i in range(8):  # frames 33 ms apart: files start at frame 0 and frame 4 (132 ms, the first >= 100 ms in)
        _write(out, _frame(i))
        _write(out, _imu(i * 10))  # IMU never starts a file, however late
    assert out.files == 2 and progress.calls == 1  # the first file finished at the split
    assert out.finish() is None and out.finish() is None  # twice is harmless
    paths = [tmp_path / "out_0000.mcap", tmp_path / "out_0001.mcap"]
    assert out.paths == paths
    total = 0
    for k, p in enumerate(paths):
        s = summarize(p)
        assert s.complete and {"device", "calibration", "config", "recording"} <= set(s.metadata)
        rec = s.metadata["recording"]
        assert rec["file_index"] == str(k) and rec["dropped_total"] == "7" and rec["wall_s"] == "1.500"
        assert rec["stop_reason"] == "split"  # progress said "" (recording goes on)
        msgs = list(read_messages(p))
        assert json.loads(rec["messages"]) == {t: sum(m.topic == t for m in msgs) for t in {m.topic for m in msgs}}
        (tf,) = [m for m in msgs if m.topic == T.TF_STATIC.name]
        assert tf.log_time_ns == int(rec["first_stamp_ns"]) == min(m.log_time_ns for m in msgs
                                                                   if m.topic != T.GYRO.name)
        children = {c for _, c, _ in posemsgs.tf_transforms(codec.decode(tf.data, T.TF_STATIC.msgtype))}
        assert {"camera_gyro_optical_frame", "camera_color_optical_frame"} <= children
        total += len(msgs)
    assert [summarize(p).topics[T.COLOR_JPEG.name].count for p in paths] == [4, 4]
    assert summarize(paths[1]).metadata["recording"]["first_stamp_ns"] == str(_frame(4).stamp_ns)
    assert out.messages == out.closed_messages == total == out.flushed_messages
    assert out.bytes_written == out.closed_bytes == sum(p.stat().st_size for p in paths)


def test_output_splits_by_size(tmp_path):
    out = _output(tmp_path, _Progress(), split_size=150_000, chunk_size=50_000)
    raw = Encoding(color_codec="raw")
    for i in range(12):
        _write(out, _frame(i, size=(96, 96)), raw)
    assert out.finish() is None
    assert len(out.paths) >= 3  # 12 frames of ~46 kB
    assert all(p.stat().st_size < 2 * 150_000 for p in out.paths)
    assert sum(summarize(p).topics[T.COLOR.name].count for p in out.paths) == 12


class _FullDisk:
    def __init__(self, budget: int, *, stays_full: bool) -> None:
        self.budget, self.stays_full, self.failed, self.real = budget, stays_full, 0, recordfile.write_all

    def __call__(self, fd, data) -> None:
        if len(data) <= self.budget and not (self.failed and self.stays_full):
            self.budget -= len(data)
            self.real(fd, data)
            return
        self.failed += 1
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("stays_full", [False, True])
def test_output_write_failure_names_what_was_written(tmp_path, monkeypatch, stays_full):
    progress = _Progress()
    out = _output(tmp_path, progress, chunk_size=20_000)
    monkeypatch.setattr(recordfile, "write_all", _FullDisk(60_000, stays_full=stays_full))
    raw = Encoding(color_codec="raw")
    with pytest.raises(DiskFull, match=r"^disk full: recording stopped after \d+ messages$") as info:
        for i in range(40):
            _write(out, _frame(i, size=(64, 64)), raw)
    written = int(str(info.value).split("after ")[1].split()[0])
    assert 0 < written == out.messages
    progress.stop_reason = str(info.value)
    err = out.finish()
    monkeypatch.undo()
    s = summarize(tmp_path / "out_0000.mcap")
    if stays_full:  # no room for a footer either: the finish error says how to get it back
        assert isinstance(err, RecorderError) and "octolog recover" in str(err) and not s.complete
    else:
        assert err is None and s.complete
    assert 0 < sum(t.count for t in s.topics.values()) <= written


def test_output_first_file_cannot_be_created(tmp_path):
    (tmp_path / "blocker").write_text("a file, not a folder")
    out = SplitMcapOutput(lambda i: tmp_path / "blocker" / "x.mcap", compression="lz4", chunk_size=1 << 20,
                          split_size=0, split_ns=0, min_free=0, metadata={}, transforms=[], progress=_Progress())
    with pytest.raises(RecorderError, match="cannot create") as info:
        _write(out, _frame(0))
    assert type(info.value) is RecorderError  # not a write failure: nothing was recorded
    assert out.paths == [] and out.finish() is None


def test_output_disk_check_stops_before_the_disk_is_full(tmp_path):
    out = _output(tmp_path, _Progress(), min_free=1)
    _write(out, _frame(0))
    out.check_disk()  # there is more than a byte free
    assert out.free_bytes > 0
    big = _output(tmp_path, _Progress(), min_free=out.free_bytes * 1000, name="big")
    _write(big, _frame(0))
    with pytest.raises(RecorderError, match=r"^disk nearly full .*big_0000\.mcap is complete$"):
        big.check_disk()
    assert big.finish() is None and summarize(tmp_path / "big_0000.mcap").complete
    first = tf_static(camera_transforms(_device(), FRAMES), 5)
    assert first.topic is T.TF_STATIC and first.stamp_ns == 5
