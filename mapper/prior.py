"""A map to start from (`mapper.prior`): the map an earlier session built, extended by this one.

The earlier session's log holds every keyframe its tracker sent and every correction (`KeyframePoses`),
in the order its mapper took them; taking them again, in that order, rebuilds that mapper's map
keyframe by keyframe (the same keyframe clouds, at the same final poses). A tracker given the same
session's SLAM map (`tracker.map`) numbers its new keyframes after the saved ones and may correct
the saved ones too: both land in this one map. Its frame (`map` -> `world`) is the earlier session's
(`octolog run --map` gives the mapper that session's `grid_up`).
"""

from __future__ import annotations

from pathlib import Path

from octolog.kit.errors import InputError, MapError
from octolog.kit.mcaplog import read_wire, summarize
from octolog.mapper.core import Mapper
from octolog.schemas import codec, posemsgs, rgbdmsgs
from octolog.schemas.topics import KEYFRAME, KEYFRAME_COMPRESSED, KEYFRAME_POSES

LOG = "session.mcap"


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
