"""The codec core: ROS 2 messages through rosbags' type store, CDR on the wire and in MCAP.

Our own types are `.msg` files beside this module; a schema change is a new type, never an edit.
Builders and readers of the messages themselves live per area (streammsgs, posemsgs, imagemsgs,
rgbdmsgs, mapmsgs); their classes are in msgtypes.
"""

from __future__ import annotations

from typing import Any

from rosbags.typesys.store import Typestore

from octolog.kit.errors import InputError
from octolog.schemas.msgtypes import Header, Time
from octolog.schemas.typestore import MSG_DIR, OWN_PACKAGE, STORE, VENDORED  # noqa: F401  (codec's names)


def typestore() -> Typestore:
    """The type store: ROS 2 (Jazzy) standard types and octolog's own (schemas/typestore.py)."""
    return STORE


def msgtype(name: str) -> Any:  # Any: a class made at run time (own types: a Protocol in msgtypes)
    """The class of `name` in the type store (a run-time lookup: msgtypes has the typed classes)."""
    return typestore().types[name]


def encode(msg: object, typename: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, typename))


def decode(data: bytes | memoryview, typename: str) -> Any:
    """The message of `typename` in `data` (its class is the store's, known only at run time)."""
    try:
        return typestore().deserialize_cdr(data, typename)
    except Exception as exc:  # rosbags raises several types for short or garbled buffers
        raise InputError(f"cannot decode {typename}: {exc}") from None


def msgdef(typename: str) -> str:
    """The ros2msg schema text MCAP files carry for a type."""
    return typestore().generate_msgdef(typename, ros_version=2)[0]


def header(stamp_ns: int, frame_id: str = "") -> Header:
    return Header(stamp=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000), frame_id=frame_id)


def stamp_ns(hdr: Header) -> int:
    return int(hdr.stamp.sec) * 1_000_000_000 + int(hdr.stamp.nanosec)
