"""Fuzzing the decoders and readers (hypothesis): hostile bytes give a known, one-line error or a
clean result, never a crash, a hang or a forged allocation.

Each target starts from a valid input octolog itself writes (a wire message, a session log, a
bag, a TUM list, a config file, a Zenoh config) and mutates it: bytes overwritten, inserted,
cut short; and from nothing (random bytes or text). The property: the reader either succeeds or
raises an OctologError (the family `octolog` prints as one line); anything else is a crash.

Budget: `OCTOLOG_FUZZ_EXAMPLES` inputs per target (default 60, derandomized: CI tries the same
inputs every run). The long run (docs/results.md, "Fuzzing") is
`OCTOLOG_FUZZ_EXAMPLES=5000 OCTOLOG_FUZZ_SEED=random pytest tests/kit/test_fuzz.py`. A crash found
becomes an `@example` of its target, so it is tried on every run from then on.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from functools import cache
from pathlib import Path

import numpy as np
from helpers import random_frame
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from octolog.kit.errors import OctologError
from octolog.schemas import codec, mapmsgs, posemsgs, rgbdmsgs, streammsgs, topics, wirecompression

EXAMPLES = int(os.environ.get("OCTOLOG_FUZZ_EXAMPLES", "60"))
settings.register_profile("octolog", max_examples=EXAMPLES, deadline=None, database=None,
                          derandomize=os.environ.get("OCTOLOG_FUZZ_SEED") != "random",
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile("octolog")


@st.composite
def mutated(draw, base: bytes) -> bytes:
    """`base` with a few bytes overwritten, a run inserted or removed, and maybe cut short."""
    data = bytearray(base)
    for _ in range(draw(st.integers(0, 6))):
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        kind = draw(st.sampled_from(["set", "insert", "delete", "max"]))
        if kind == "set":
            data[i] = draw(st.integers(0, 255))
        elif kind == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "delete":
            del data[i:i + draw(st.integers(1, 16))]
        else:  # a length or size field blown up
            data[i:i + 4] = b"\xff\xff\xff\x7f"
    if draw(st.booleans()):
        data = data[:draw(st.integers(0, len(data)))]
    return bytes(data)


def hostile(base: bytes, *, max_random: int = 4096) -> st.SearchStrategy[bytes]:
    return st.one_of(mutated(base), st.binary(max_size=max_random))


def _wire_samples() -> dict[topics.Topic, bytes]:
    f, pose = random_frame(4, stamp_ns=5_000_000_000), np.eye(4)
    png = wirecompression.parse_wire_compression("png")
    jpeg = wirecompression.parse_wire_compression("jpeg")
    msgs = {
        topics.RGBD: rgbdmsgs.rgbd_msg(f),
        topics.RGBD_COMPRESSED: rgbdmsgs.compressed_rgbd_msg(f, jpeg),
        topics.KEYFRAME: rgbdmsgs.keyframe_msg(1, pose, f),
        topics.KEYFRAME_COMPRESSED: rgbdmsgs.compressed_keyframe_msg(1, pose, f, png),
        topics.KEYFRAME_POSES: posemsgs.keyframe_poses_msg({1: pose, 2: pose}, 7),
        topics.RGBD_END: streammsgs.stream_end_msg(topics.RGBD.name, 3),
        topics.POSE: posemsgs.pose_stamped_msg(pose, 7),
        topics.OCCUPIED: mapmsgs.point_cloud_msg(np.ones((5, 3), np.float32), 7),
    }
    return {t: codec.encode(m, t.msgtype) for t, m in msgs.items()}


WIRE = _wire_samples()


def _consume(topic: topics.Topic, msg) -> None:
    """What the stages do with an admitted message of `topic`."""
    if topic in (topics.RGBD, topics.RGBD_COMPRESSED):
        rgbdmsgs.rgbd_from_msg(msg)
    elif topic in (topics.KEYFRAME, topics.KEYFRAME_COMPRESSED):
        rgbdmsgs.keyframe_from_msg(msg)
    elif topic == topics.KEYFRAME_POSES:
        posemsgs.keyframe_poses_from_msg(msg)
    elif topic == topics.RGBD_END:
        int(msg.count), str(msg.topic)
    elif topic == topics.POSE:
        posemsgs.pose_matrix(msg.pose)
    elif topic == topics.OCCUPIED:
        mapmsgs.point_cloud_xyz(msg)


def _zero_quaternion() -> bytes:
    msg = posemsgs.keyframe_poses_msg({1: np.eye(4)}, 7)
    msg.world_from_camera[0].orientation.w = 0.0
    return codec.encode(msg, topics.KEYFRAME_POSES.msgtype)


@given(st.sampled_from(sorted(WIRE, key=lambda t: t.name)).flatmap(lambda t: st.tuples(st.just(t), hostile(WIRE[t]))))
@example((topics.KEYFRAME_POSES, _zero_quaternion()))  # found: scipy's ValueError for a zero quaternion
def test_wire_messages_are_screened_or_consumed(sample):
    """CDR decode of every message type the stages take, the bus's checks, then the stage's own
    conversion: a malformed sample is dropped at the bus or refused with an InputError."""
    from octolog.kit.bus.inbox import Received
    from octolog.kit.bus.screening import Screening

    topic, payload = sample
    admitted = Screening("fuzz", "").admit(Received(topic, payload))
    if admitted is not None:
        try:
            _consume(topic, admitted.msg)
        except OctologError:
            pass


# --- files ---------------------------------------------------------------------------------------

@cache
def _session_log() -> bytes:
    from octolog.kit.mcaplog import McapWriter

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.mcap"
        with McapWriter(path, compression="lz4", chunk_size=2048) as w:
            w.add_metadata("octolog", {"version": "fuzz"})
            for i in range(6):
                w.write(topics.RGBD.name, topics.RGBD.msgtype, WIRE[topics.RGBD], log_time_ns=i, publish_time_ns=i)
                w.write(topics.RGBD_END.name, topics.RGBD_END.msgtype, WIRE[topics.RGBD_END], log_time_ns=i,
                        publish_time_ns=i)
        return path.read_bytes()


def _scratch() -> Path:
    return Path(tempfile.mkdtemp(prefix="octolog-fuzz-"))


def _forged_length() -> bytes:
    log = bytearray(_session_log())
    log[9:17] = (2**31 - 1).to_bytes(8, "little")  # the header record's length: 2 GB in a small file
    return bytes(log)


@given(hostile(_session_log(), max_random=2048))
@example(b"")
@example(b"\x00")  # found: struct.error from the reader's magic check
@example(_session_log()[:2000])  # found: lz4's RuntimeError for a cut chunk
@example(_forged_length())  # found: MemoryError, the reader allocating a forged record length
def test_mcap_readers_and_recover(data):
    """summarize, message_counts, time_span, read_messages and `recover` on a damaged session log."""
    from octolog.kit.mcaplog import message_counts, read_messages, read_wire, summarize, time_span
    from octolog.recorder.recover import recover

    d = _scratch()
    try:
        src = d / "in.mcap"
        src.write_bytes(data)
        for read in (summarize, message_counts, time_span, lambda p: list(read_messages(p)),
                     lambda p: list(read_messages(p, [topics.RGBD.name])), lambda p: list(read_wire(p)),
                     lambda p: list(read_wire(p, [topics.RGBD.name]))):
            try:
                read(src)
            except OctologError:
                pass
        try:
            recover(src, d / "out.mcap")
        except OctologError:
            assert not (d / "out.mcap").exists()  # nothing half-written under the asked name
        else:
            assert summarize(d / "out.mcap").complete
    finally:
        shutil.rmtree(d)


@cache
def _bags() -> dict[str, bytes]:
    from helpers.recordings import write_ros1_bag, write_ros2_bag

    with tempfile.TemporaryDirectory() as d:
        write_ros1_bag(Path(d) / "a.bag")
        write_ros2_bag(Path(d) / "b", names={"color": "/camera/color/image_raw",
                                              "depth": "/camera/aligned_depth_to_color/image_raw",
                                              "info": "/camera/color/camera_info", "imu": "/camera/imu"}, n=2)
        db3 = next((Path(d) / "b").glob("*.db3"))
        return {"bag": (Path(d) / "a.bag").read_bytes(), "db3": db3.read_bytes(),
                "yaml": (Path(d) / "b" / "metadata.yaml").read_bytes()}


@given(st.sampled_from(["bag", "db3", "yaml"]).flatmap(lambda k: st.tuples(st.just(k), mutated(_bags()[k]))))
def test_bag_import(sample):
    """`octolog import` of a damaged ROS 1 bag, rosbag2 .db3 or its metadata.yaml."""
    from octolog.recorder.importers import import_source

    kind, data = sample
    d = _scratch()
    try:
        if kind == "bag":
            src = d / "in.bag"
            src.write_bytes(data)
        else:
            src = d / "in"
            src.mkdir()
            (src / "metadata.yaml").write_bytes(data if kind == "yaml" else _bags()["yaml"])
            (src / "b_0.db3").write_bytes(data if kind == "db3" else _bags()["db3"])
        try:
            import_source(src, d / "out.mcap")
        except OctologError:
            pass
    finally:
        shutil.rmtree(d)


TUM_LIST = b"# colour images\n# file: 'x.bag'\n# timestamp filename\n1305031102.175304 rgb/1.png\n" \
           b"1305031102.211214 rgb/2.png\n"


@given(st.one_of(mutated(TUM_LIST), st.text(max_size=300).map(str.encode)))
@example(b"\x80")  # found: UnicodeDecodeError
@example(b"1e400 rgb/1.png\n")  # found: OverflowError from a stamp past int64 nanoseconds
@example(b"Infinity rgb/1.png\n")
def test_tum_lists(data):
    """A TUM folder whose rgb.txt (or groundtruth.txt) is damaged: open_tum and read_tum."""
    from octolog.kit.metrics import read_tum
    from octolog.kit.tum import open_tum

    d = _scratch()
    try:
        (d / "rgb.txt").write_bytes(data)
        (d / "depth.txt").write_bytes(TUM_LIST.replace(b"rgb/", b"depth/"))
        (d / "groundtruth.txt").write_bytes(data)
        for read in (lambda: open_tum(d, camera="freiburg1"), lambda: read_tum(d / "groundtruth.txt")):
            try:
                read()
            except OctologError:
                pass
    finally:
        shutil.rmtree(d)


CONFIG = b'[replay]\nrate = 1.0\nevery = 2\n\n[tracker]\nn_features = 800\nlive = false\n\n[mapper]\nresolution_m = 0.05\n'


@given(st.one_of(mutated(CONFIG), st.text(max_size=300).map(str.encode)))
@example(b"\x80")  # found: UnicodeDecodeError
def test_config_files(data):
    """A damaged config file, loaded for each stage as `--config` does."""
    from octolog.kit.config import load
    from octolog.mapper.config import MapperConfig
    from octolog.replay.config import ReplayConfig
    from octolog.tracker.config import TrackerConfig

    d = _scratch()
    try:
        (d / "c.toml").write_bytes(data)
        for cls, section in ((ReplayConfig, "replay"), (TrackerConfig, "tracker"), (MapperConfig, "mapper")):
            try:
                load(cls, d / "c.toml", section=section)
            except OctologError:
                pass
    finally:
        shutil.rmtree(d)


ZENOH = (Path(__file__).resolve().parents[2] / "docs" / "examples" / "zenoh-tls-client.json5").read_bytes()


@given(st.one_of(mutated(ZENOH), st.text(max_size=300).map(str.encode)))
def test_zenoh_config_files(data):
    """A damaged Zenoh JSON5 file (`--zenoh-config`): parsed into a Zenoh config, or a BusError."""
    from octolog.kit.bus.session import zenoh_config
    from octolog.kit.busconfig import BusConfig

    d = _scratch()
    try:
        (d / "z.json5").write_bytes(data)
        try:
            zenoh_config(BusConfig(mode="client", connect=("tcp/127.0.0.1:1",), zenoh_config=str(d / "z.json5")))
        except OctologError:
            pass
    finally:
        shutil.rmtree(d)
