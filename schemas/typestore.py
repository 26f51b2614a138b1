"""The one rosbags type store every octolog process encodes, decodes and builds messages with.

It holds the ROS 2 standard types the wire contract uses (`stocktypes.FIELDDEFS`, Jazzy's) and
octolog's own (`msg/*.msg`; a schema change is a new type, never an edit), and is built once on
import: msgtypes takes the message classes from it and codec serialises with it, so a decoded
message is an instance of the class msgtypes names.
"""

from __future__ import annotations

from pathlib import Path

from rosbags.interfaces.typing import Typesdict
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from octolog.schemas.stocktypes import FIELDDEFS

MSG_DIR = Path(__file__).with_name("msg")
OWN_PACKAGE = "octolog_msgs"
# Types from outside ROS 2's core that we vendor as .msg text.
VENDORED = {"Octomap": "octomap_msgs"}


def _build() -> Typestore:
    store = get_typestore(Stores.EMPTY)
    store.register(FIELDDEFS)
    own: Typesdict = {}
    for path in sorted(MSG_DIR.glob("*.msg")):
        pkg = VENDORED.get(path.stem, OWN_PACKAGE)
        own.update(get_types_from_msg(path.read_text(), f"{pkg}/msg/{path.stem}"))
    store.register(own)
    return store


STORE = _build()
