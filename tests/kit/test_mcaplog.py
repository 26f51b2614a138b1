from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from octolog.kit.errors import McapError
from octolog.kit.geometry import pose_to_matrix
from octolog.kit.mcaplog import McapWriter, read_messages, salvage, summarize, time_span
from octolog.schemas import codec, posemsgs, topics


def _write(path: Path, n: int, compression: str) -> list[bytes]:
    payloads = []
    with McapWriter(path, compression=compression, chunk_size=4096) as w:
        w.add_metadata("config", {"tracker": '{"n_features": 1000}'})
        for i in range(n):
            T = pose_to_matrix(np.array([i * 0.1, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
            data = codec.encode(posemsgs.pose_stamped_msg(T, 1_000 + i), topics.POSE.msgtype)
            payloads.append(data)
            w.write(topics.POSE.name, topics.POSE.msgtype, data, log_time_ns=1_000 + i, publish_time_ns=1_000 + i)
    return payloads


@pytest.mark.parametrize("compression", ["none", "lz4", "zstd"])
def test_round_trip_every_compression(tmp_path, compression):
    path = tmp_path / "a.mcap"
    payloads = _write(path, 50, compression)
    got = list(read_messages(path))
    assert [m.data for m in got] == payloads
    assert all(m.topic == "tracker/pose" and m.msgtype == topics.POSE.msgtype for m in got)
    s = summarize(path)
    assert s.complete and s.profile == "ros2"
    assert s.topics["tracker/pose"].count == 50
    assert s.metadata["config"] == {"tracker": '{"n_features": 1000}'}
    assert time_span(path) == (1_000, 1_049)  # from the summary section, as the scan has it


def test_rosbags_reads_our_file_without_our_types(tmp_path):
    from rosbags.highlevel import AnyReader

    path = tmp_path / "a.mcap"
    _write(path, 5, "zstd")
    with AnyReader([path]) as reader:
        (conn,) = reader.connections
        assert (conn.topic, conn.msgtype, conn.msgcount) == ("/tracker/pose", "geometry_msgs/msg/PoseStamped", 5)
        xs = [reader.deserialize(raw, conn.msgtype).pose.position.x for _, _, raw in reader.messages()]
    assert xs == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])


def test_truncated_file_is_reported_not_crashed(tmp_path):
    path = tmp_path / "a.mcap"
    _write(path, 200, "none")
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    s = summarize(cut)
    assert not s.complete and s.problem
    assert time_span(cut) is None  # no summary section: nothing to read the span from
    assert 0 < s.topics["tracker/pose"].count < 200
    with pytest.raises(McapError, match=r"cut\.mcap: truncated or corrupt MCAP \(after \d+ messages.*`octolog recover "):
        list(read_messages(cut))


def test_missing_and_non_mcap_files(tmp_path):
    with pytest.raises(McapError, match="no such MCAP file"):
        list(read_messages(tmp_path / "none.mcap"))
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(McapError, match="junk.mcap"):
        list(read_messages(junk))
    # random bytes are no recording, not a damaged one: nothing to summarise or recover
    with pytest.raises(McapError, match=r"junk\.mcap: not an MCAP file \(no MCAP magic at its start\)"):
        summarize(junk)


@pytest.mark.parametrize("compression", ["none", "lz4", "zstd"])
def test_salvage_keeps_every_whole_chunk_of_a_cut_file(tmp_path, compression):
    """A file cut mid-chunk: every message of its whole chunks, its metadata and the caller's, in a
    complete file; the uncut file comes through whole."""
    src = tmp_path / "a.mcap"
    payloads = _write(src, 400, compression)
    whole = salvage(src, tmp_path / "whole.mcap")
    assert (whole.complete, whole.messages, whole.metadata) == (True, 400, 1)
    assert [m.data for m in read_messages(tmp_path / "whole.mcap")] == payloads
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    res = salvage(cut, tmp_path / "out.mcap", extra_metadata=lambda r: {"recovery": {"messages": str(r.messages)}})
    assert not res.complete and res.problem and 0 < res.chunks and 0 < res.messages < 400
    assert res.bytes_read <= res.source_bytes == len(data) // 2
    got = list(read_messages(tmp_path / "out.mcap"))
    assert [m.data for m in got] == payloads[: res.messages]
    s = summarize(tmp_path / "out.mcap")
    assert s.complete and s.metadata["recovery"] == {"messages": str(res.messages)}
    assert s.metadata["config"] == {"tracker": '{"n_features": 1000}'}
