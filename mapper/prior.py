"""A map to start from (`mapper.prior`): the map an earlier session built, extended by this one.

The earlier session's log holds every keyframe its tracker sent and every correction (`KeyframePoses`),
in the order its mapper took them; taking them again, in that order, rebuilds that mapper's map
keyframe by keyframe (the same keyframe clouds, at the same final poses). A tracker given the same
session's SLAM map (`tracker.map`) numbers its new keyframes after the saved ones and may correct
the saved ones too: both land in this one map. Its frame (`map` -> `world`) is the earlier session's
(`octolog run --map` gives the mapper that session's `grid_up`).
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from octolog.kit.errors import InputError, MapError
from octolog.kit.mcaplog import read_wire, summarize
from octolog.mapper.core import Mapper
from octolog.schemas import codec, posemsgs, rgbdmsgs
from octolog.schemas.topics import KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_POSES

LOG = "session.mcap"


class PriorSeed:
    """The map to start from, taken when the tracker shows it tracks in that session's world.

    The tracker's first item decides: a keyframe numbered below the saved map's keyframes means the
    tracker did not find the camera in the saved map and started a map of its own (its keyframes
    are numbered from 0 again), so the earlier map is left out and this session's map is its own;
    anything else (a keyframe after the saved ones, a correction of saved ones) means it did, and
    the earlier map goes in first. A stream with no keyframe at all (localizing) ends with the
    earlier map. The decision depends on the stream's contents only, so a replay decides the same.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        log = self.folder / LOG
        if not log.is_file():
            raise InputError(f"mapper.prior {folder}: no {LOG} there (the folder of an earlier `octolog run`)")
        summary = summarize(log)
        if not summary.complete:
            raise InputError(f"mapper.prior {log}: truncated or corrupt (`octolog info` shows what is readable)")
        topics = summary.wire_topics
        self.keyframes = sum(t.count for name, t in topics.items() if name in (KEYFRAME.name, KEYFRAME_COMPRESSED.name))
        if self.keyframes == 0:
            raise InputError(f"mapper.prior {log}: no keyframes in it (a log without the tracker's output?)")
        try:
            up = tomllib.loads((self.folder / "config.toml").read_text()).get("mapper", {}).get("grid_up")
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"mapper.prior {folder}: unreadable config.toml ({exc})") from None
        self.up = tuple(float(v) for v in up) if up else None  # that session's map frame
        self.pending = True
        self.taken = 0  # keyframes taken from it (0: left out)
        self.note = ""

    def decide(self, mapper: Mapper, first_keyframe_id: int | None) -> bool:
        """Take the earlier map or leave it out, on the tracker's first item (`first_keyframe_id`:
        a keyframe's id, None for a correction or the end of a stream without items). Returns
        whether it was taken."""
        self.pending = False
        if first_keyframe_id is not None and first_keyframe_id < self.keyframes:
            self.note = (f"the tracker did not find the camera in {self.folder}'s map (its first keyframe is "
                         f"{first_keyframe_id}): this map is the session's own")
            return False
        if self.up is not None:
            mapper.set_up(self.up)
        self.taken = seed(mapper, self.folder)
        return True


def seed(mapper: Mapper, folder: str | Path) -> int:
    """Integrate the keyframes of the session in `folder` (its session log) and apply its
    corrections, in log order; returns the keyframes taken. InputError naming what is missing."""
    log = Path(folder) / LOG
    if not log.is_file():
        raise InputError(f"mapper.prior {folder}: no {LOG} there (the folder of an earlier `octolog run`)")
    if not summarize(log).complete:
        raise InputError(f"mapper.prior {log}: truncated or corrupt (`octolog info` shows what is readable)")
    n = 0
    for m in read_wire(log, [KEYFRAME.name, KEYFRAME_COMPRESSED.name, KEYFRAME_POSES.name]):
        msg = codec.decode(m.data, m.msgtype)
        try:
            if m.topic == KEYFRAME_POSES.name:
                mapper.correct(posemsgs.keyframe_poses_from_msg(msg), msg.depth_inverse_offset)
                continue
            kf_id, pose, frame = rgbdmsgs.keyframe_from_msg(msg)
            mapper.integrate(kf_id, pose, frame)
            n += 1
        except (InputError, MapError) as exc:
            raise InputError(f"mapper.prior {log}: {exc}") from None
    if n == 0:
        raise InputError(f"mapper.prior {log}: no keyframes in it (a log without the tracker's output?)")
    return n
