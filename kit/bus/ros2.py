"""ROS 2 without ROS: octolog's standard-typed topics also published the way rmw_zenoh publishes.

ROS 2's Zenoh middleware (rmw_zenoh, Jazzy and later) does not use zenoh-bridge-ros2dds's plain
keys (`tracker/pose`): a ROS 2 subscription to `/tracker/pose` of type geometry_msgs/msg/PoseStamped
listens on

    <domain>/tracker/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_<sha256 of the type>

and reads each sample's attachment (sequence number, source timestamp, publisher GID, serialised
with zenoh-ext's serializer). The ROS graph (`ros2 topic list`, `ros2 topic echo` without a type)
comes from liveliness tokens under `@ros2_lv/<domain>/...`. With `BusConfig.ros2_domain` set
(`--ros2-domain N`), every octolog publisher of a standard ROS type also puts its CDR bytes (the
same bytes: ROS 2 CDR is octolog's wire format) on that key, and each stage declares a node and its
publishers in the ROS graph. Topics of octolog's own types (octolog_msgs) stay on octolog's keys
only: a ROS 2 node would need our message packages to read them.

The type hash is RIHS01 (REP 2011), computed by rosbags from the message definitions; the test
checks it against the hashes ROS 2 Jazzy publishes for standard types.
"""

from __future__ import annotations

import time
from functools import cache

from octolog.kit.bus.session import LatchedPublisher, Session, ZenohPublisher, ext_deserialize, ext_serialize
from octolog.schemas import codec

ADMIN_SPACE = "@ros2_lv"
# rmw_zenoh's QoS field: reliability:durability:history,depth:deadline:lifespan:liveliness, each
# empty where it is the default (reliable, volatile, keep last; depth 10 is written out)
QOS_DEFAULT = "::,10:,:,:,,"
# /tf_static as tf2's StaticTransformBroadcaster declares it: reliable, TRANSIENT_LOCAL (1), keep last 1
QOS_LATCHED = ":1:,1:,:,:,,"
# octolog topics a ROS 2 node expects latched (durability TRANSIENT_LOCAL): rmw_zenoh serves a late
# subscription from the publisher's cache (zenoh-ext's AdvancedPublisher, depth samples)
LATCHED = frozenset({"tf_static"})
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE since Iron


def is_ros_type(msgtype: str) -> bool:
    """A type a ROS 2 installation has (not one of octolog's own)."""
    return not msgtype.startswith("octolog_msgs/")


@cache
def type_hash(msgtype: str) -> str:
    """The RIHS01 hash of a message type, as ROS 2 announces it (`RIHS01_<64 hex>`)."""
    return codec.typestore().hash_rihs01(msgtype)


def dds_type_name(msgtype: str) -> str:
    """`geometry_msgs/msg/PoseStamped` -> `geometry_msgs::msg::dds_::PoseStamped_`."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_key(domain: int, ros_name: str, msgtype: str) -> str:
    """The Zenoh key rmw_zenoh publishes and subscribes a topic on."""
    return f"{domain}/{ros_name.strip('/')}/{dds_type_name(msgtype)}/{type_hash(msgtype)}"


def mangle(name: str) -> str:
    """A ROS name as one key chunk: `/` becomes `%` (the empty name too)."""
    return name.replace("/", "%") or "%"


def node_token(domain: int, zid: str, node_id: int, node_name: str) -> str:
    return f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{node_id}/NN/%/%/{node_name}"


def publisher_token(domain: int, zid: str, node_id: int, entity_id: int, node_name: str, ros_name: str,
                    msgtype: str, qos: str = QOS_DEFAULT) -> str:
    return (f"{ADMIN_SPACE}/{domain}/{zid}/{node_id}/{entity_id}/MP/%/%/{node_name}/{mangle(ros_name)}/"
            f"{dds_type_name(msgtype)}/{type_hash(msgtype)}/{qos}")


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's sample attachment: key, value pairs in zenoh-ext's serialisation."""
    assert len(gid) == GID_SIZE
    return ext_serialize(("sequence_number", seq, "source_timestamp", stamp_ns, "source_gid", gid))


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh attachment; ValueError if it is not one."""
    try:
        k1, seq, k2, stamp, k3, gid = ext_deserialize(data, (str, int, str, int, str, bytes))
    except ValueError as exc:
        raise ValueError(f"not an rmw_zenoh attachment: {exc}") from None
    if (k1, k2, k3) != ("sequence_number", "source_timestamp", "source_gid") or len(gid) != GID_SIZE:
        raise ValueError("not an rmw_zenoh attachment: unexpected keys or GID size")
    return int(seq), int(stamp), gid


class Ros2Node:
    """A stage as a node in the ROS graph of one domain: its token, and one mirror per publisher."""

    def __init__(self, session: Session, domain: int, stage: str) -> None:
        self._session, self.domain = session, domain
        self.name = f"octolog_{stage or 'node'}"
        self._zid = session.zid()
        self._entities = 0
        session.declare_token(node_token(domain, self._zid, 0, self.name))

    def mirror(self, ros_name: str, msgtype: str, gid: bytes, *, latched: bool = False) -> Ros2Mirror:
        """A publisher on the rmw_zenoh key. `latched`: TRANSIENT_LOCAL depth 1, as rmw_zenoh (Jazzy,
        since its AdvancedPublisher change) declares it: a cache of the last sample that a late
        subscription's history query reads, and a liveliness token so it finds late publishers."""
        self._entities += 1
        key = topic_key(self.domain, ros_name, msgtype)
        self._session.declare_token(publisher_token(self.domain, self._zid, 0, self._entities, self.name,
                                                    ros_name, msgtype, QOS_LATCHED if latched else QOS_DEFAULT))
        pub = self._session.declare_latched_publisher(key) if latched else self._session.declare_publisher(key)
        return Ros2Mirror(pub, gid[:GID_SIZE].ljust(GID_SIZE, b"\0"))


class Ros2Mirror:
    """Puts what an octolog publisher sends on the rmw_zenoh key too, numbered as rmw_zenoh numbers."""

    def __init__(self, pub: ZenohPublisher | LatchedPublisher, gid: bytes) -> None:
        self._pub, self._gid, self._seq = pub, gid, 0

    def put(self, data: bytes) -> None:
        self._seq += 1  # rmw_zenoh counts from 1
        self._pub.put(data, attachment=attachment(self._seq, time.time_ns(), self._gid))
