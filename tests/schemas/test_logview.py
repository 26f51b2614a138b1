"""The session log's standard view (octolog.schemas.logview): every octolog message stored as
standard ROS 2 parts, joined back byte for byte."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolog.kit import depthmodel
from octolog.kit.errors import InputError
from octolog.kit.mcaplog import McapWriter, read_messages, read_wire, summarize
from octolog.replay.sources import SyntheticSource
from octolog.schemas import codec, logview, posemsgs, rgbdmsgs, streammsgs, topics, wirecompression


def _round_trip(topic: topics.Topic, msg: object) -> list[tuple[str, str, bytes]]:
    data = codec.encode(msg, topic.msgtype)
    parts = logview.split(topic.name, topic.msgtype, data)
    assert all(not t.startswith(codec.OWN_PACKAGE) for _, t, _ in parts)  # standard types only
    assert parts[-1][:2] == (topic.name, logview.DIAGNOSTICS)
    assert logview.join(topic.msgtype, parts[-1][2], {name: d for name, _, d in parts[:-1]}) == data
    return parts


@pytest.fixture(scope="module")
def frame():
    return next(SyntheticSource(2).frames())


def test_frames_and_keyframes_keep_their_bytes(frame):
    jpeg = wirecompression.parse_wire_compression("jpeg:80,png")
    parts = _round_trip(topics.RGBD, rgbdmsgs.rgbd_msg(frame))
    assert [(n, t) for n, t, _ in parts[:-1]] == [
        ("camera/color/image_raw", "sensor_msgs/msg/Image"),
        ("camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image"),
        ("camera/color/camera_info", "sensor_msgs/msg/CameraInfo")]
    parts = _round_trip(topics.RGBD_COMPRESSED, rgbdmsgs.compressed_rgbd_msg(frame, jpeg))
    colour = codec.decode(parts[0][2], "sensor_msgs/msg/CompressedImage")
    assert parts[0][0] == "camera/color/image_raw/compressed" and "jpeg" in colour.format
    T = np.eye(4)
    T[:3, 3] = (0.1, -2.5, 1e-9)
    parts = _round_trip(topics.KEYFRAME, rgbdmsgs.keyframe_msg(2**63 + 5, T, frame))
    pose = codec.decode(next(d for n, _, d in parts if n == "tracker/keyframe/pose"), logview.POSE_STAMPED)
    assert pose.header.frame_id == "world" and np.allclose(posemsgs.pose_matrix(pose.pose), T)
    _round_trip(topics.KEYFRAME_COMPRESSED, rgbdmsgs.compressed_keyframe_msg(7, T, frame, jpeg))


def test_bookkeeping_messages_become_diagnostics():
    Status = codec.msgtype(topics.TRACKING_STATUS.msgtype)
    for state, level in ((Status.INIT, 1), (Status.OK, 0), (Status.LOST, 2), (Status.SKIPPED, 1),
                         (Status.INERTIAL, 1)):
        msg = Status(header=codec.header(12, "cam"), seq=2**64 - 1, state=state, is_keyframe=True,
                     keyframe_id=-1, n_matches=3, n_inliers=2, processing_ms=0.1,
                     map_moved_m=0.0, relocalised=state == Status.OK, imu_gyro_count=7, imu_accel_count=2**32 - 1)
        (part,) = _round_trip(topics.TRACKING_STATUS, msg)
        diag = codec.decode(part[2], logview.DIAGNOSTICS)
        assert diag.status[0].level == level and diag.status[0].message == topics.TRACKING_STATUS.msgtype
        assert {kv.key: kv.value for kv in diag.status[0].values}["seq"] == str(2**64 - 1)
    _round_trip(topics.RGBD_END, streammsgs.stream_end_msg("camera/rgbd/ümlaut \"quoted\"", 300, 5))
    _round_trip(topics.CAMERA_PROPERTIES, streammsgs.camera_properties_msg("D455", 1 / 3))
    _round_trip(topics.CAMERA_PROPERTIES, streammsgs.camera_properties_msg("D455", 0.0, 7, depthmodel.d455(382.0)))
    parts = _round_trip(topics.KEYFRAME_POSES, posemsgs.keyframe_poses_msg({3: np.eye(4), 1: np.eye(4)}))
    assert parts[0][:2] == ("tracker/keyframe_poses/poses", logview.POSE_ARRAY)
    _round_trip(topics.KEYFRAME_POSES, posemsgs.keyframe_poses_msg({}))


def test_a_status_logged_before_its_later_fields_existed_reads_as_no_correction():
    """A field added to a wire type later (logview.ADDED_FIELDS) is absent from older logs: such a
    message reads with the field's stated default, not as a broken log."""
    Status = codec.msgtype(topics.TRACKING_STATUS.msgtype)
    msg = Status(header=codec.header(12, "cam"), seq=4, state=Status.OK, is_keyframe=False, keyframe_id=-1,
                 n_matches=3, n_inliers=2, processing_ms=0.1, map_moved_m=0.25, relocalised=True,
                 imu_gyro_count=40, imu_accel_count=20)
    (part,) = logview.split(topics.TRACKING_STATUS.name, topics.TRACKING_STATUS.msgtype, codec.encode(
        msg, topics.TRACKING_STATUS.msgtype))
    diag = codec.decode(part[2], logview.DIAGNOSTICS)
    diag.status[0].values = [kv for kv in diag.status[0].values
                             if kv.key not in ("map_moved_m", "relocalised", "imu_gyro_count",
                                               "imu_accel_count")]  # an older log
    old = codec.decode(logview.join(topics.TRACKING_STATUS.msgtype, codec.encode(diag, logview.DIAGNOSTICS), {}),
                       topics.TRACKING_STATUS.msgtype)
    assert (old.seq, old.n_inliers, old.map_moved_m, old.relocalised) == (4, 2, 0.0, False)
    assert (old.imu_gyro_count, old.imu_accel_count) == (0, 0)


@given(st.floats(allow_nan=True, allow_infinity=True), st.integers(0, 2**64 - 1), st.integers(0, 2**32 - 1))
def test_any_field_value_survives(ms, big, small):
    msg = codec.msgtype(topics.MAP_UPDATE.msgtype)(header=codec.header(small, "map"), keyframe_id=big,
                                                    n_points=small, n_occupied=big, n_free=0, processing_ms=ms)
    data = codec.encode(msg, topics.MAP_UPDATE.msgtype)
    (part,) = logview.split(topics.MAP_UPDATE.name, topics.MAP_UPDATE.msgtype, data)
    back = logview.join(topics.MAP_UPDATE.msgtype, part[2], {})
    if math.isnan(ms):  # NaN != NaN: compare the payload bit patterns instead
        assert back[:-8] == data[:-8] and math.isnan(codec.decode(back, topics.MAP_UPDATE.msgtype).processing_ms)
    else:
        assert back == data


def test_every_own_type_on_the_bus_has_a_standard_form():
    for topic in topics.ALL:
        if logview.is_split(topic.msgtype):
            logview._residual_fields(topic.msgtype)  # raises for a nested field without a standard part
        else:
            assert topic.msgtype in codec.typestore().types


def test_standard_types_pass_through():
    data = codec.encode(posemsgs.pose_stamped_msg(np.eye(4), 1), topics.POSE.msgtype)
    assert logview.split(topics.POSE.name, topics.POSE.msgtype, data) == [(topics.POSE.name, topics.POSE.msgtype, data)]


def _log(path, frames, *, drop: str | None = None) -> None:
    with McapWriter(path) as w:
        for f in frames:
            data = codec.encode(rgbdmsgs.rgbd_msg(f), topics.RGBD.msgtype)
            for name, msgtype, part in logview.split(topics.RGBD.name, topics.RGBD.msgtype, data):
                if name != drop:
                    w.write(name, msgtype, part, log_time_ns=f.stamp_ns, publish_time_ns=f.stamp_ns)
            pose = codec.encode(posemsgs.pose_stamped_msg(np.eye(4), f.stamp_ns), topics.POSE.msgtype)
            w.write(topics.POSE.name, topics.POSE.msgtype, pose, log_time_ns=f.stamp_ns, publish_time_ns=f.stamp_ns)


def test_the_wire_view_of_a_log(tmp_path):
    frames = list(SyntheticSource(3).frames())
    _log(tmp_path / "s.mcap", frames)
    wire = list(read_wire(tmp_path / "s.mcap", [topics.RGBD.name]))
    assert [m.data for m in wire] == [codec.encode(rgbdmsgs.rgbd_msg(f), topics.RGBD.msgtype) for f in frames]
    assert {m.msgtype for m in wire} == {topics.RGBD.msgtype}
    assert [m.topic for m in read_wire(tmp_path / "s.mcap")] == [topics.RGBD.name, topics.POSE.name] * 3
    # a part asked for by name is still given (a recording's images are read the same way)
    assert len(list(read_wire(tmp_path / "s.mcap", [topics.COLOR.name]))) == 3
    s = summarize(tmp_path / "s.mcap")
    assert s.topics[topics.RGBD.name].msgtype == logview.DIAGNOSTICS
    assert s.wire_topics[topics.RGBD.name].msgtype == topics.RGBD.msgtype
    assert len(list(read_messages(tmp_path / "s.mcap"))) == 3 * 5


def test_a_log_missing_a_part_is_named(tmp_path):
    _log(tmp_path / "s.mcap", list(SyntheticSource(2).frames()), drop="camera/color/camera_info")
    with pytest.raises(InputError, match=r"/camera/rgbd message 0: .*without its /camera/color/camera_info part"):
        list(read_wire(tmp_path / "s.mcap", [topics.RGBD.name]))


def test_a_log_of_the_old_layout_reads_the_same(tmp_path):
    """Before the standard view the logger stored octolog types as they were: still read as wire."""
    frames = list(SyntheticSource(2).frames())
    payloads = [codec.encode(rgbdmsgs.rgbd_msg(f), topics.RGBD.msgtype) for f in frames]
    with McapWriter(tmp_path / "old.mcap") as w:
        for f, data in zip(frames, payloads, strict=True):
            w.write(topics.RGBD.name, topics.RGBD.msgtype, data, log_time_ns=f.stamp_ns, publish_time_ns=f.stamp_ns)
    assert [m.data for m in read_wire(tmp_path / "old.mcap", [topics.RGBD.name])] == payloads
    assert summarize(tmp_path / "old.mcap").wire_topics[topics.RGBD.name].msgtype == topics.RGBD.msgtype


def test_a_diagnostic_array_naming_an_unknown_type_is_left_as_it_is(tmp_path):
    """A log from a newer octolog (or a hostile one) naming a type this one does not know: the
    message is passed on as the DiagnosticArray it is, not joined, not a crash."""
    Status = codec.msgtype("diagnostic_msgs/msg/DiagnosticStatus")
    diag = codec.msgtype(logview.DIAGNOSTICS)(header=codec.header(1, ""), status=[Status(
        level=0, name="tracker/status", message="octolog_msgs/msg/FromTheFuture", hardware_id="octolog", values=[])])
    data = codec.encode(diag, logview.DIAGNOSTICS)
    with McapWriter(tmp_path / "s.mcap") as w:
        w.write("tracker/status", logview.DIAGNOSTICS, data, log_time_ns=1, publish_time_ns=1)
    (m,) = read_wire(tmp_path / "s.mcap")
    assert m.msgtype == logview.DIAGNOSTICS and m.data == data
