"""ROS 2 reach without ROS (octolog.kit.bus.ros2): the keys, type hashes, attachments and graph
tokens of rmw_zenoh, checked against what ROS 2 Jazzy publishes, and a real run seen by a
subscriber that knows only what a ROS 2 node knows (topic name, type, the type's hash)."""

from __future__ import annotations

import struct
import subprocess
import sys
import threading

import pytest
import zenoh
from helpers import ROOT
from rosbags.typesys import Stores, get_typestore

from octolog.kit.bus import ros2
from octolog.kit.busconfig import BusConfig
from octolog.kit.errors import BusError

# As ROS 2 Jazzy announces them (`ros2 topic info -v` prints "Topic type hash"; the same values are
# in each package's share/<pkg>/msg/<Type>.json): not computed here, copied from ROS.
PUBLISHED = {
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "geometry_msgs/msg/PoseStamped": "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CameraInfo": "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "sensor_msgs/msg/CompressedImage": "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    "sensor_msgs/msg/Imu": "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
    "std_msgs/msg/Header": "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
}


@pytest.mark.parametrize("msgtype", sorted(PUBLISHED))
def test_type_hashes_are_the_ones_ros2_publishes(msgtype: str) -> None:
    assert ros2.type_hash(msgtype) == PUBLISHED[msgtype]


def test_keys_and_graph_tokens_follow_rmw_zenoh() -> None:
    """The talker/listener example of rmw_zenoh's design notes (Jazzy), rebuilt from its parts."""
    string = "std_msgs::msg::dds_::String_/" + PUBLISHED["std_msgs/msg/String"]
    assert ros2.topic_key(0, "/chatter", "std_msgs/msg/String") == f"0/chatter/{string}"
    assert ros2.topic_key(7, "/robot1/tracker/pose", "geometry_msgs/msg/PoseStamped") == \
        "7/robot1/tracker/pose/geometry_msgs::msg::dds_::PoseStamped_/" + PUBLISHED["geometry_msgs/msg/PoseStamped"]
    zid = "aac3178e146ba6f1fc6e6a4085e77f21"
    assert ros2.node_token(0, zid, 0, "listener") == f"@ros2_lv/0/{zid}/0/0/NN/%/%/listener"
    assert ros2.publisher_token(0, zid, 0, 10, "talker", "/chatter", "std_msgs/msg/String") == \
        f"@ros2_lv/0/{zid}/0/10/MP/%/%/talker/%chatter/{string}/::,10:,:,:,,"


def test_the_attachment_is_rmw_zenohs_layout() -> None:
    """rmw_zenoh (attachment_helpers.cpp) writes, with zenoh-ext's serializer: the string
    "sequence_number", an int64, "source_timestamp", an int64, "source_gid", 16 bytes; strings and
    byte arrays are prefixed by their length (LEB128), integers little-endian."""
    gid = bytes(range(16))
    data = ros2.attachment(3, 1_700_000_000_123_456_789, gid)
    expected = (b"\x0fsequence_number" + struct.pack("<q", 3) + b"\x10source_timestamp"
                + struct.pack("<q", 1_700_000_000_123_456_789) + b"\x0asource_gid" + b"\x10" + gid)
    assert data == expected
    assert ros2.parse_attachment(data) == (3, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError, match="not an rmw_zenoh attachment"):
        ros2.parse_attachment(data[:-3])


def test_a_domain_out_of_range_is_refused() -> None:
    with pytest.raises(BusError, match="--ros2-domain 233"):
        BusConfig(ros2_domain=233).validate()


def test_a_ros2_subscriber_sees_a_runs_pose_and_grid(router, tmp_path) -> None:
    """`octolog run --ros2-domain 0` on the synthetic room: a plain Zenoh subscriber on the keys a
    ROS 2 node with rmw_zenoh would use for /tracker/pose, /tf and /mapper/grid gets every pose and the
    grids, readable with rosbags' stock Jazzy types and numbered as rmw_zenoh numbers; the ROS graph
    lists the stages' nodes and publishers. Topics of octolog's own types stay off the ROS keys."""
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    pose_key = "0/tracker/pose/geometry_msgs::msg::dds_::PoseStamped_/" + PUBLISHED["geometry_msgs/msg/PoseStamped"]
    got: dict[str, list[tuple[bytes, bytes]]] = {"pose": [], "grid": [], "tf": [], "other": []}
    tokens: set[str] = set()
    lock = threading.Lock()

    def keep(name: str):
        def on(sample: zenoh.Sample) -> None:
            with lock:
                got[name].append((sample.payload.to_bytes(), sample.attachment.to_bytes()))
        return on

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{router}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as z:
        subs = [z.declare_subscriber(pose_key, keep("pose")),
                z.declare_subscriber("0/mapper/grid/nav_msgs::msg::dds_::OccupancyGrid_/*", keep("grid")),
                z.declare_subscriber("0/tf/tf2_msgs::msg::dds_::TFMessage_/*", keep("tf")),
                z.declare_subscriber("0/camera/rgbd/**", keep("other")),
                z.liveliness().declare_subscriber("@ros2_lv/0/**", lambda s: tokens.add(str(s.key_expr)))]
        out = tmp_path / "s"
        proc = subprocess.run([sys.executable, "-m", "octolog", "run", "--source", "synthetic:40", "--out", str(out),
                               "--rerun", "off", "--quiet", "--router", router, "--ros2-domain", "0"],
                              cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)
        assert proc.returncode == 0, proc.stderr
        del subs
    stamps = [line.split()[0] for line in (out / "trajectory.txt").read_text().splitlines() if line.strip()]
    assert len(got["pose"]) == len(stamps) == 40
    seqs = []
    for data, att in got["pose"]:
        msg = jazzy.deserialize_cdr(data, "geometry_msgs/msg/PoseStamped")
        assert f"{msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d}" in stamps
        seq, stamp_ns, gid = ros2.parse_attachment(att)
        seqs.append(seq)
        assert stamp_ns > 0 and len(gid) == 16
    assert seqs == list(range(1, 41))
    assert got["grid"], "no grid on the ROS 2 key"
    grid = jazzy.deserialize_cdr(got["grid"][-1][0], "nav_msgs/msg/OccupancyGrid")
    assert grid.info.width * grid.info.height == len(grid.data) > 0
    assert got["other"] == []  # octolog_msgs/RgbdFrame: no ROS 2 key
    assert len(got["tf"]) == 40  # the camera's tree (camera_link) in `world`, every frame
    tf = jazzy.deserialize_cdr(got["tf"][0][0], "tf2_msgs/msg/TFMessage").transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("world", "camera_link")
    nodes = {t.rsplit("/", 1)[1] for t in tokens if "/NN/" in t}
    assert {"octolog_tracker", "octolog_mapper"} <= nodes
    assert any(t.endswith(f"/MP/%/%/octolog_tracker/%tracker%pose/{pose_key.split('/', 3)[3]}/::,10:,:,:,,")
               for t in tokens), sorted(tokens)


def test_tf_static_is_latched_for_a_ros2_node_that_joins_late(router) -> None:
    """/tf_static as ROS 2 expects it (TRANSIENT_LOCAL, depth 1): a subscription that joins after the
    mapper announced `map` -> `world` still gets it, asking as an rmw_zenoh subscription does
    (zenoh-ext's AdvancedSubscriber with history, detecting late publishers), and the graph token
    says TRANSIENT_LOCAL. A volatile topic's publisher keeps nothing for it."""
    import queue

    import numpy as np
    import zenoh.ext

    from octolog.kit.bus import Bus
    from octolog.schemas import posemsgs
    from octolog.schemas.topics import POSE, TF_STATIC

    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, 1.25)
    tf_key = "0/tf_static/tf2_msgs::msg::dds_::TFMessage_/" + ros2.type_hash("tf2_msgs/msg/TFMessage")
    pose_key = "0/tracker/pose/geometry_msgs::msg::dds_::PoseStamped_/" + PUBLISHED["geometry_msgs/msg/PoseStamped"]
    cfg = BusConfig(mode="client", connect=(router,), multicast_scouting=False, ros2_domain=0)
    got: queue.Queue = queue.Queue()
    with Bus(cfg, "mapper") as bus:
        bus.publisher(TF_STATIC).put(posemsgs.tf_msg([("map", "world", T)], 0))
        bus.publisher(POSE).put(posemsgs.pose_stamped_msg(T, 7))  # volatile: a late subscription gets none
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", f'["{router}"]')
        conf.insert_json5("scouting/multicast/enabled", "false")
        with zenoh.open(conf) as z:
            tokens = [str(r.ok.key_expr) for r in z.liveliness().get("@ros2_lv/0/**") if r.ok is not None]
            history = zenoh.ext.HistoryConfig(detect_late_publishers=True)
            subs = [zenoh.ext.declare_advanced_subscriber(z, key, lambda s, k=key: got.put((k, s.payload.to_bytes(),
                                                                                           s.attachment.to_bytes())),
                                                          history=history)
                    for key in (tf_key, pose_key)]
            key, data, att = got.get(timeout=30)
            del subs
    assert key == tf_key
    tf = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(data, "tf2_msgs/msg/TFMessage").transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id, tf.transform.translation.z) == ("map", "world", 1.25)
    assert ros2.parse_attachment(att)[0] == 1
    assert got.empty()
    latched = [t for t in tokens if "/%tf_static/" in t]
    assert latched and all(t.endswith("/" + ros2.QOS_LATCHED) for t in latched), tokens
