"""The recorder on pyrealsense2's software device: every pushed sample in the file, drops counted,
crash safety (SIGKILL, full disk), clean stops, live publishing, bad input."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from helpers import free_port
from helpers.recordings import SOFTWARE, record_software

from octolog.kit import mcaplog, recordfile
from octolog.kit.config import to_json
from octolog.kit.errors import ConfigError, McapError, RecorderError
from octolog.kit.mcaplog import read_messages, summarize
from octolog.recorder import node
from octolog.recorder.capture import Capture, CaptureProfile
from octolog.recorder.config import RecorderConfig, SoftwareConfig, make_recorder
from octolog.recorder.realsense_camera import NO_DEVICE, RealSenseBackend
from octolog.recorder.recording_types import JPEG_FORMAT, PNG_FORMAT, output_paths
from octolog.recorder.recover import recover
from octolog.recorder.software_d455 import SoftwareDeviceBackend, SyntheticPattern
from octolog.schemas import codec, imagecodec, rgbdmsgs, sensormsgs, wirecompression
from octolog.schemas import topics as T

ROOT = Path(__file__).resolve().parents[2]
def _by_topic(path: Path) -> dict[str, list[mcaplog.LoggedMessage]]:
    out: dict[str, list[mcaplog.LoggedMessage]] = {}
    for m in read_messages(path):
        out.setdefault(m.topic, []).append(m)
    return out


def _check_file(path: Path, backend: SoftwareDeviceBackend, cfg: RecorderConfig, *, exact_images: int) -> None:
    """Every pushed sample is in the file with its sensor time, values, calibration, metadata."""
    s = summarize(path)
    assert s.complete and s.profile == "ros2", s.problem
    msgs = _by_topic(path)
    pushed: dict[str, list] = {}
    for p in backend.pushed:
        pushed.setdefault(p.stream, []).append(p)
    scene = backend.pattern
    assert scene is not None
    color_topic = T.COLOR_JPEG if cfg.color_codec == "jpeg" else T.COLOR
    depth_topics = []
    if cfg.aligned_depth:
        depth_topics.append(("aligned", T.ALIGNED_DEPTH_PNG if cfg.depth_codec == "png" else T.ALIGNED_DEPTH,
                             T.ALIGNED_DEPTH_INFO))
    if cfg.raw_depth:
        depth_topics.append(("raw", T.DEPTH_PNG if cfg.depth_codec == "png" else T.DEPTH, T.DEPTH_INFO))

    def image(m: mcaplog.LoggedMessage, topic: T.Topic) -> tuple[int, np.ndarray]:
        msg = codec.decode(m.data, topic.msgtype)
        assert m.log_time_ns == codec.stamp_ns(msg.header) == m.publish_time_ns
        if topic.msgtype.endswith("CompressedImage"):
            assert msg.format in (JPEG_FORMAT, PNG_FORMAT)
            return codec.stamp_ns(msg.header), imagecodec.compressed_image_array(msg)
        return codec.stamp_ns(msg.header), sensormsgs.image_array(msg)

    # colour: every frame, in order, with its time; raw bit-exact, JPEG close
    colors = msgs[color_topic.name]
    assert [image(m, color_topic)[0] for m in colors] == [p.stamp_ns for p in pushed["color"]]
    for i in range(min(exact_images, len(colors))):
        _, rgb = image(colors[i], color_topic)
        want = scene.color(i)
        if cfg.color_codec == "raw":
            assert np.array_equal(rgb, want)
        else:
            # lossy (4:2:0, q95 on a noisy pattern), but this frame and not its neighbour
            err = np.abs(rgb.astype(int) - want).mean()
            assert err < 5.0 and err < 0.5 * np.abs(rgb.astype(int) - scene.color(i + 1)).mean()
    # depth: aligned and/or raw, every frame; raw depth bit-exact through raw and PNG alike
    for kind, topic, info_topic in depth_topics:
        got = msgs[topic.name]
        assert [image(m, topic)[0] for m in got] == [p.stamp_ns for p in pushed["depth"]]
        for i in range(min(exact_images, len(got))):
            _, d = image(got[i], topic)
            assert d.dtype == np.uint16
            if kind == "raw":
                assert np.array_equal(d, scene.depth(i))
            else:
                assert d.shape == (cfg.color.height, cfg.color.width) and (d > 0).mean() > 0.5
        infos = [codec.decode(m.data, info_topic.msgtype) for m in msgs[info_topic.name]]
        assert len(infos) == len(got)
    # calibration with every colour frame
    infos = [codec.decode(m.data, T.COLOR_INFO.msgtype) for m in msgs[T.COLOR_INFO.name]]
    assert [codec.stamp_ns(i.header) for i in infos] == [p.stamp_ns for p in pushed["color"]]
    intr = sensormsgs.intrinsics_from(infos[0])
    assert (intr.width, intr.height, intr.fx) == (cfg.color.width, cfg.color.height, pytest.approx(640.0))
    # IMU: every sample, its time and its float32 values
    for stream, topic in (("gyro", T.GYRO), ("accel", T.ACCEL)):
        got = [codec.decode(m.data, topic.msgtype) for m in msgs[topic.name]]
        assert [codec.stamp_ns(g.header) for g in got] == [p.stamp_ns for p in pushed[stream]]
        assert [p.frame_number for p in pushed[stream]] == list(range(len(got)))
        for k in (0, len(got) // 2, len(got) - 1):
            v = got[k].angular_velocity if stream == "gyro" else got[k].linear_acceleration
            assert (v.x, v.y, v.z) == SyntheticPattern.motion(stream, k)
    # static transforms once, metadata
    (tf,) = [codec.decode(m.data, T.TF_STATIC.msgtype) for m in msgs[T.TF_STATIC.name]]
    children = {t.child_frame_id for t in tf.transforms}
    assert {"camera_depth_optical_frame", "camera_color_optical_frame", "camera_gyro_optical_frame"} <= children
    md = s.metadata
    assert md["device"]["serial"] == backend.serial and md["device"]["firmware"]
    assert md["calibration"]["depth_scale_m"] == "0.001"
    assert json.loads(md["calibration"]["color_from_depth"])[0][3] == pytest.approx(-0.059, abs=1e-6)
    assert set(json.loads(md["calibration"]["imu_intrinsics"])) == {"gyro", "accel"}
    assert md["config"]["recorder"] == to_json(cfg)
    streams = json.loads(md["recording"]["streams"])
    assert streams["color"]["frames"] == len(pushed["color"]) and md["recording"]["dropped_total"] == "0"


COMBOS = [(c, d, z) for c in ("jpeg", "raw") for d in ("png", "raw") for z in ("lz4", "zstd", "none")]


@pytest.mark.slow
@pytest.mark.parametrize("color_codec,depth_codec,compression", COMBOS)
def test_every_pushed_sample_is_recorded(tmp_path, color_codec, depth_codec, compression):
    """Every combination at the D455 default profile; the default one for 10 s of sensor time (300
    frame pairs, 2000 gyro, 1000 accel samples), the others, which also record raw depth, for 1 s
    (what a codec does to a frame it does to the 30th as to the 300th)."""
    default = (color_codec, depth_codec, compression) == (SOFTWARE.color_codec, SOFTWARE.depth_codec, SOFTWARE.compression)
    frames = 300 if default else 30
    cfg = dataclasses.replace(SOFTWARE, color_codec=color_codec, depth_codec=depth_codec, compression=compression,
                              raw_depth=not default)
    backend, res = record_software(tmp_path, cfg, frames=frames)
    assert res.stop_reason == "end of stream" and res.dropped == 0
    assert res.streams["color"].frames == frames == len([p for p in backend.pushed if p.stream == "color"])
    seconds = frames / SOFTWARE.color.fps
    assert (res.last_stamp_ns - res.first_stamp_ns) >= (seconds - 0.1) * 1e9
    gyro_hz, accel_hz = 200, 100
    assert res.streams["gyro"].frames >= (seconds - 0.05) * gyro_hz
    assert res.streams["accel"].frames >= (seconds - 0.1) * accel_hz
    _check_file(res.paths[0], backend, cfg, exact_images=5)


def test_same_input_same_payloads(tmp_path):
    cfg = dataclasses.replace(SOFTWARE, raw_depth=True)
    runs = []
    for name in ("a.mcap", "b.mcap"):
        _, res = record_software(tmp_path, cfg, frames=12, name=name)
        runs.append([(m.topic, m.log_time_ns, m.data) for m in read_messages(res.paths[0])])
    assert runs[0] == runs[1]


def test_duration_is_sensor_time(tmp_path):
    _, res = record_software(tmp_path, frames=0, duration_s=0.5)
    assert res.stop_reason == "duration reached"
    assert res.streams["color"].frames == 15 and res.streams["gyro"].frames == 100


def test_split_by_duration_and_size(tmp_path):
    cfg = dataclasses.replace(SOFTWARE, split_duration_s=0.5)
    _, res = record_software(tmp_path, cfg, frames=40)
    assert [p.name for p in res.paths] == ["rec_0000.mcap", "rec_0001.mcap", "rec_0002.mcap"]
    stamps = []
    for p in res.paths:
        s = summarize(p)
        assert s.complete and {"device", "calibration", "config", "recording"} <= set(s.metadata)
        assert s.topics[T.TF_STATIC.name].count == 1
        stamps += [m.log_time_ns for m in read_messages(p, [T.COLOR_JPEG.name])]
    assert len(stamps) == 40 and stamps == sorted(stamps)
    cfg = dataclasses.replace(SOFTWARE, split_size_mb=4.0, chunk_size_mb=1.0)
    _, res = record_software(tmp_path, cfg, frames=30, name="s.mcap")
    assert len(res.paths) >= 3
    assert sum(summarize(p).topics[T.COLOR_JPEG.name].count for p in res.paths) == 30


def test_writer_behind_drops_are_counted_not_silent(tmp_path, monkeypatch):
    """A real-time source and a stalled writer: what the queue cannot hold is counted per stream."""
    from octolog.recorder.writer import Recorder

    gate = threading.Event()
    real_encode = Recorder._encode

    def stalled(self, cap):
        if threading.current_thread() is not threading.main_thread():  # not the set-up's warm-up encode
            gate.wait(30)
        return real_encode(self, cap)

    monkeypatch.setattr(Recorder, "_encode", stalled)
    backend = SoftwareDeviceBackend(frames=40)
    backend.realtime = True  # a camera: the recorder must not make it wait
    real_wait = backend.wait

    def wait(timeout_s):
        out = real_wait(timeout_s)
        if backend._done:  # the camera has given its last frame: the writer may go on
            gate.set()
        return out

    backend.wait = wait  # type: ignore[method-assign]
    cfg = dataclasses.replace(SOFTWARE, queue_frames=3, encode_threads=1)
    res = node.run(cfg, tmp_path / "d.mcap", backend=backend)
    st = res.streams["color"]
    assert st.queue_drops > 0 and st.frames + st.queue_drops == 40
    assert res.streams["aligned_depth"].frames + res.streams["aligned_depth"].queue_drops == 40
    rec = summarize(res.paths[0]).metadata["recording"]
    assert json.loads(rec["streams"])["color"]["queue_drops"] == st.queue_drops
    assert int(rec["dropped_total"]) == res.dropped > 0
    assert summarize(res.paths[0]).topics[T.COLOR_JPEG.name].count == st.frames


def test_device_frame_gaps_are_counted(tmp_path):
    b = SoftwareDeviceBackend(frames=1)
    device = b.open(CaptureProfile())
    b.close()
    rec = make_recorder(SOFTWARE, output_paths(tmp_path / "g.mcap", split=False, overwrite=False), device)
    for fn in (0, 1, 4, 5, 9):
        rec.submit(Capture(seen=[("color", fn), ("depth", fn)]))
    rec.close("test")
    assert rec.stats["color"].device_gaps == 5 and rec.stats["depth"].device_gaps == 5


# --- crash safety ----------------------------------------------------------------------------------


def _spawn(tmp_path: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "octolog", "record", *args], cwd=ROOT,
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


class _Lines:
    """stderr status lines of a child, read on a thread; wait for one matching a predicate."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        try:
            for line in proc.stderr:
                with self._cond:
                    self.lines.append(line.rstrip())
                    self._cond.notify_all()
        except (ValueError, OSError):
            pass  # the pipe closed under us: the test is over

    def wait(self, pred, timeout_s: float = 60.0) -> str:
        with self._cond:
            assert self._cond.wait_for(lambda: any(pred(x) for x in self.lines), timeout_s), self.lines[-5:]
            return next(x for x in self.lines if pred(x))


def _on_disk(line: str) -> int:
    return int(line.rsplit("(", 1)[1].split()[0]) if "on disk)" in line else -1


# the software D455 filming its flat pattern, not the rendered room (shell/simcamera.py): these test
# the recorder, and start at once
PATTERN = ("--set", 'software.scene="pattern"')


def test_sigkill_mid_recording_then_recover(tmp_path):
    from octolog.shell.info import describe

    out = tmp_path / "killed.mcap"
    proc = _spawn(tmp_path, str(out), "--backend", "software", "--set", "chunk_size_mb=1", "--set",
                  "raw_depth=true", *PATTERN)
    lines = _Lines(proc)
    line = lines.wait(lambda x: _on_disk(x) >= 400)
    reported = _on_disk(line)
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)
    s = summarize(out)
    assert not s.complete
    readable = sum(t.count for t in s.topics.values())
    assert readable >= reported
    assert "INCOMPLETE" in describe(out) and "readable" in describe(out)
    r = recover(out, tmp_path / "fixed.mcap")
    assert not r.source_complete and r.messages == readable
    f = summarize(tmp_path / "fixed.mcap")
    assert f.complete and sum(t.count for t in f.topics.values()) == readable
    assert {"device", "calibration", "config", "recovery"} <= set(f.metadata)
    assert f.metadata["recovery"]["messages"] == str(readable)
    # at most the unfinished chunk (1 MB, a few frames) is lost: colour and depth stay in step
    c, d = f.topics[T.COLOR_JPEG.name].count, f.topics[T.DEPTH.name].count
    assert c > 10 and abs(c - d) <= 3
    with pytest.raises(McapError, match="exists"):
        recover(out, tmp_path / "fixed.mcap")


def test_sigterm_finishes_the_file(tmp_path):
    out = tmp_path / "term.mcap"
    proc = _spawn(tmp_path, str(out), "--backend", "software", *PATTERN)
    lines = _Lines(proc)
    lines.wait(lambda x: _on_disk(x) > 0)
    proc.send_signal(signal.SIGTERM)
    stdout, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, lines.lines[-3:]
    assert "stopped: interrupted" in stdout
    s = summarize(out)
    assert s.complete and s.metadata["recording"]["stop_reason"] == "interrupted"


class _FullDisk:
    """Stands in for os.write in McapWriter: fails with ENOSPC once `budget` bytes are written,
    after writing part of the failing block (a torn write), then maybe recovers."""

    def __init__(self, budget: int, *, stays_full: bool) -> None:
        self.budget = budget
        self.stays_full = stays_full
        self.failed = 0
        self.real = recordfile.write_all

    def __call__(self, fd: int, data) -> None:
        if len(data) <= self.budget and not (self.failed and self.stays_full):
            self.budget -= len(data)
            self.real(fd, data)
            return
        self.real(fd, bytes(data)[: self.budget // 2])
        self.failed += 1
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("stays_full", [False, True])
def test_disk_full_stops_cleanly(tmp_path, monkeypatch, stays_full):
    full = _FullDisk(12_000_000, stays_full=stays_full)
    monkeypatch.setattr(recordfile, "write_all", full)
    cfg = dataclasses.replace(SOFTWARE, chunk_size_mb=1.0)
    out = tmp_path / "full.mcap"
    with pytest.raises(RecorderError) as info:
        record_software(tmp_path, cfg, frames=0, name=out.name)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("disk full")
    monkeypatch.undo()
    s = summarize(out)
    n = sum(t.count for t in s.topics.values())
    assert n > 50 and s.topics[T.COLOR_JPEG.name].count > 3
    if stays_full:  # could not even finish: the file is a clean prefix, recover makes it whole
        assert "octolog recover" in msg and not s.complete
        r = recover(out, tmp_path / "fixed.mcap")
        assert r.messages == n and summarize(tmp_path / "fixed.mcap").complete
    else:  # finished with a footer; readers scan it (no index after a failed chunk)
        assert "is finished" in msg and s.complete
        assert len(list(read_messages(out))) == n


@pytest.fixture
def tiny_disk(tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a size-limited tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    yield mnt
    subprocess.run(["umount", str(mnt)], check=False)


@pytest.mark.root
def test_real_full_disk(tiny_disk):
    """A 24 MB tmpfs: with the free-space reserve off, ENOSPC itself; with it, a stop before."""
    with pytest.raises(RecorderError, match="^disk full") as info:
        record_software(tiny_disk, dataclasses.replace(SOFTWARE, min_free_mb=0.0, chunk_size_mb=1.0), frames=0, name="a.mcap")
    assert "is finished" in str(info.value)
    s = summarize(tiny_disk / "a.mcap")
    assert s.complete and s.topics[T.COLOR_JPEG.name].count > 3
    (tiny_disk / "a.mcap").unlink()
    with pytest.raises(RecorderError, match="^disk nearly full"):
        record_software(tiny_disk, dataclasses.replace(SOFTWARE, min_free_mb=12.0, chunk_size_mb=1.0), frames=0, name="b.mcap")
    s = summarize(tiny_disk / "b.mcap")
    assert s.complete and s.metadata["recording"]["stop_reason"].startswith("disk nearly full")


# --- bad input ---------------------------------------------------------------------------------------


def test_no_camera_is_one_line():
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is attached")
    with pytest.raises(RecorderError, match="^no RealSense device found") as info:
        RealSenseBackend().open(CaptureProfile())
    assert "\n" not in str(info.value)


def test_no_camera_cli(tmp_path):
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is attached")
    r = subprocess.run([sys.executable, "-m", "octolog", "record", str(tmp_path / "x.mcap")], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and r.stderr.strip() == \
        "octolog record: error: no RealSense device found (is the camera plugged in, and does " \
        "`rs-enumerate-devices` list it?); without one, the simulated D455 stands in: " \
        "`octolog record --backend software`, `octolog run --source d455:software`"
    assert not (tmp_path / "x.mcap").exists()
    # the whole pipeline on it: the same one line, nothing else said, no session folder
    r = subprocess.run([sys.executable, "-m", "octolog", "run", "--source", "d455", "--out", str(tmp_path / "s")],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and r.stderr.strip() == "octolog run: error: " + NO_DEVICE and r.stdout == ""
    assert not (tmp_path / "s").exists()


def test_unplugged_mid_recording(tmp_path):
    cfg = dataclasses.replace(SOFTWARE, software=SoftwareConfig(unplug_after=20))
    out = tmp_path / "rec.mcap"
    with pytest.raises(RecorderError, match="disconnected") as info:
        record_software(tmp_path, cfg, frames=0)
    assert "\n" not in str(info.value) and "after 20 frames" in str(info.value)
    s = summarize(out)
    assert s.complete and s.topics[T.COLOR_JPEG.name].count == 20
    assert s.metadata["recording"]["stop_reason"].startswith("device lost")


@pytest.mark.parametrize("change,expect", [
    ({"color": dataclasses.replace(SOFTWARE.color, width=1920, height=1080)},
     r"colour 1920x1080@30 is not supported .*supported \(rgb8\): 1280x800@5/15/30, 1280x720@5/15/30"),
    ({"depth": dataclasses.replace(SOFTWARE.depth, fps=45)}, r"depth 848x480@45 is not supported .*848x480@5/15/30/60/90"),
    ({"gyro_fps": 300}, r"gyro at 300 Hz is not supported .*200/400 Hz"),
    ({"accel_fps": 63}, r"accel at 63 Hz is not supported .*100/200 Hz"),
    ({"depth_units_m": 0.5}, r"depth_units_m=0.5: outside the device's range"),
])
def test_unsupported_profile_lists_what_is(tmp_path, change, expect):
    with pytest.raises(RecorderError, match=expect) as info:
        record_software(tmp_path, dataclasses.replace(SOFTWARE, **change), frames=3)
    assert "\n" not in str(info.value)
    assert not (tmp_path / "rec.mcap").exists()


def test_existing_output_needs_overwrite(tmp_path):
    (tmp_path / "rec.mcap").write_bytes(b"precious")
    with pytest.raises(RecorderError, match="exists; pass --overwrite"):
        record_software(tmp_path, frames=3)
    assert (tmp_path / "rec.mcap").read_bytes() == b"precious"
    _, res = record_software(tmp_path, frames=3, overwrite=True)
    assert summarize(res.paths[0]).complete


def test_options_and_config_errors(tmp_path):
    cfg = dataclasses.replace(SOFTWARE, depth_units_m=0.0001, visual_preset="high_accuracy", emitter="off",
                              color_auto_exposure="off", color_exposure=300.0)
    _, res = record_software(tmp_path, cfg, frames=3)
    s = summarize(res.paths[0])
    assert s.metadata["calibration"]["depth_scale_m"] == "0.0001"
    opts = json.loads(s.metadata["device"]["options"])
    assert opts["emitter"] == 0.0 and opts["visual_preset"] == 3.0 and opts["color_exposure"] == 300.0
    with pytest.raises(ConfigError, match="recorder.visual_preset 'shiny'"):
        dataclasses.replace(SOFTWARE, visual_preset="shiny").validate()
    import argparse

    from octolog.shell.record import add_parsers, overrides

    parser = argparse.ArgumentParser()
    add_parsers(parser.add_subparsers())
    with pytest.raises(ConfigError, match="--color '1280x720': want WIDTHxHEIGHT@FPS"):
        overrides(parser.parse_args(["record", "x.mcap", "--color", "1280x720"]))
    args = parser.parse_args(["record", "x.mcap", "--color", "640x480@15", "--depth-streams", "both", "--no-imu",
                              "--emitter", "off", "--paced"])
    assert overrides(args) == ["color.width=640", "color.height=480", "color.fps=15", 'emitter="off"', "imu=false",
                               "software.paced=true", "aligned_depth=true", "raw_depth=true"]


# --- live ----------------------------------------------------------------------------------------



@pytest.mark.parametrize("wire_depth", ["zstd", "png"])
def test_publishes_live_while_recording(tmp_path, wire_depth):
    """Camera topics and camera/rgbd/compressed on Zenoh (the recorded JPEG colour as written, depth as
    lossless zstd); what a slow consumer missed is counted as live drops."""
    from octolog.kit.bus import Bus, BusConfig

    ep = f"tcp/127.0.0.1:{free_port()}"
    sub_cfg = BusConfig(listen=(ep,), multicast_scouting=False, namespace="rec")
    pub_cfg = BusConfig(connect=(ep,), multicast_scouting=False, namespace="rec")
    got: dict[str, list[bytes]] = {}
    rgbd = T.RGBD_COMPRESSED
    with Bus(sub_cfg, "tracker", inbox_size=64) as sub:
        sub.start([T.RGBD, rgbd, T.RGBD_END, T.COLOR_JPEG, T.GYRO])
        cfg = dataclasses.replace(SOFTWARE, wait_for=("tracker",), wait_timeout_s=30.0, wire_depth=wire_depth)
        result: dict = {}
        t = threading.Thread(target=lambda: result.update(res=record_software(tmp_path, cfg, frames=20, bus_cfg=pub_cfg)[1]))
        t.start()
        while T.RGBD_END.name not in got:
            r = sub.receive(30.0)
            assert r is not None, "no end message"
            got.setdefault(r.topic.name, []).append(r.payload)
    t.join(60)  # the recorder stays until its tracker (this subscriber) is done: leaving `with` says so
    res = result["res"]
    live = res.streams["color"].live_drops
    assert T.RGBD.name not in got  # JPEG colour is recorded: frames go out compressed, never raw
    assert len(got[rgbd.name]) + live == 20 == res.streams["color"].frames
    end = codec.decode(got[T.RGBD_END.name][0], T.RGBD_END.msgtype)
    assert end.topic == rgbd.name and int(end.count) == len(got[rgbd.name])
    msg = codec.decode(got[rgbd.name][0], rgbd.msgtype)
    frame = rgbdmsgs.rgbd_from_msg(msg)
    recorded = [m for m in read_messages(res.paths[0], [T.COLOR_JPEG.name])]
    assert frame.stamp_ns == recorded[0].log_time_ns and frame.depth.shape == (720, 1280)
    assert frame.depth_scale_m == pytest.approx(0.001) and frame.intrinsics.fx == pytest.approx(640.0)
    assert got[T.COLOR_JPEG.name][0] == recorded[0].data  # the same bytes as in the file
    jpeg = codec.decode(recorded[0].data, T.COLOR_JPEG.msgtype)
    assert bytes(msg.color.data) == bytes(jpeg.data)  # the frame carries the recorded JPEG, not a re-encoding
    # depth as recorder.wire_depth says, lossless: the recorded aligned depth exactly
    assert msg.depth.format == wirecompression.DEPTH_CODECS[wire_depth]
    aligned = next(read_messages(res.paths[0], [T.ALIGNED_DEPTH.name]))
    assert np.array_equal(frame.depth, sensormsgs.image_array(codec.decode(aligned.data, T.ALIGNED_DEPTH.msgtype)))


def test_rerun_logs_what_is_recorded(tmp_path):
    _, res = record_software(tmp_path, frames=5, rerun=f"save:{tmp_path / 'rr'}", recording_id="test")
    rrd = tmp_path / "rr" / "recorder.rrd"
    assert rrd.exists() and rrd.stat().st_size > 100_000
    assert summarize(res.paths[0]).complete


@pytest.mark.parametrize("depth_codec", ["raw", "png"])
def test_recordings_open_in_rosbags_and_rerun(tmp_path, depth_codec):
    """A recording reads with rosbags (no octolog types) and converts in Rerun with images and depth."""
    import os
    import re
    import subprocess
    import sys

    from rosbags.highlevel import AnyReader

    cfg = dataclasses.replace(SOFTWARE, depth_codec=depth_codec)
    record_software(tmp_path, cfg, frames=5)
    path = tmp_path / "rec.mcap"
    with AnyReader([path]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        conn = next(c for c in reader.connections if c.topic.startswith("/camera/color/image_raw"))
        first = next(reader.messages([conn]))
        assert reader.deserialize(first[2], conn.msgtype).header.stamp.sec > 0
    assert counts["/camera/color/camera_info"] == 5
    rerun = str(Path(sys.executable).with_name("rerun"))
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1"}
    rrd = tmp_path / "rec.rrd"
    subprocess.run([rerun, "mcap", "convert", str(path), "-o", str(rrd)], check=True, capture_output=True, env=env,
                   timeout=120)
    stats = subprocess.run([rerun, "rrd", "stats", str(rrd)], check=True, capture_output=True, text=True, env=env,
                           timeout=120).stdout
    entities = set(re.findall(r"^(/\S+): \d+$", stats, re.M))
    assert any(e.startswith("/camera/color/image_raw") for e in entities), entities
    assert any(e.startswith("/camera/aligned_depth_to_color/image_raw") for e in entities), entities
    colour = "EncodedImage:blob:" if cfg.color_codec == "jpeg" else "Image:buffer:"
    assert colour in stats  # colour frames as images the viewer shows
    if depth_codec == "raw":
        assert "DepthImage:buffer:" in stats  # 16UC1 becomes a depth image with its own colormap


def test_record_into_a_session_folder(tmp_path):
    """`octolog record DIR`: the recording plus its resolved config and a summary, like `octolog run`."""
    from helpers import octolog as cli

    from octolog.kit.config import load

    out = tmp_path / "field"
    cli("record", str(out), "--backend", "software", "--duration", "1", "--quiet", *PATTERN)
    assert (out / "session.mcap").is_file()
    assert load(RecorderConfig, out / "config.toml", section="recorder") == RecorderConfig(
        backend="software", software=SoftwareConfig(scene="pattern"))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dropped"] == 0 and summary["streams"]["color"]["frames"] == 30
    assert summary["stop_reason"] == "duration reached" and "numpy" in summary["versions"]
