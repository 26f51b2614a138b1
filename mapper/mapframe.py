"""The `map` frame (z up) the mapper builds in: given in the config, or found on the bus.

`octolog run` on a file finds up before the stages start (the file's accelerometer,
octolog.replay.source_gravity) and gives it as `mapper.grid_up`: the mapper announces `map` -> `world` at
once. A mapper not told `grid_up` (one started on its own, `octolog map`) finds it on the bus:
- a replay of a file serves the same up on `camera/gravity` (and publishes it before its first
  frame); the mapper asks for it when the first keyframe arrives, before integrating it, so a
  restarted mapper gets it too;
- a live camera (`octolog record` publishing, `--source d455`) is only read once it runs: the
  mapper listens to `camera/accel/sample` and the camera's `/tf_static` (outside its inbox) and
  decides at its first snapshot: the accelerometer's mean within 0.1 s of the first keyframe,
  rotated into that keyframe's optical frame and levelled on its dominant near-horizontal plane
  as a file's first frame is (octolog.kit.up_vector); the keyframes integrated so far move into the
  new frame.
A tracker with a trusted IMU then sends its own estimate (`tracker/gravity`, in `world`): gravity
from its alignments, the accelerometer's bias estimated with it, which a single mean at the first
frame cannot do. Unless up was given (`mapper.grid_up`, a prior map), the map moves onto it,
levelled on the first keyframe's horizontal plane as above; its final estimate comes after the
last keyframe, so the files are built on it.
Without either the map assumes a level first camera (up = -y), as before. What the bus gave goes
into map_stats.json (`map_frame`); `octolog run` copies it into the session's config.toml, so a
replay of the session log (which carries no IMU stream to the mapper) draws the same map.
"""

from __future__ import annotations

import numpy as np

from octolog.kit.bus import Bus
from octolog.kit.errors import InputError
from octolog.kit.geometry import RgbdFrame
from octolog.kit.up_vector import LiveUp, level_on_plane
from octolog.kit.viz import Viz
from octolog.mapper.core import Mapper
from octolog.mapper.params import DEFAULT_UP
from octolog.schemas import codec, posemsgs
from octolog.schemas.topics import ACCEL, GRAVITY, TF_STATIC


GRAVITY_WAIT_S = 1.0  # for the replay's answer on camera/gravity (a known queryable answers in ms)


class MapFrame:
    """Announces `map` -> `world` on /tf_static and in Rerun, once up is known."""

    def __init__(self, mapper: Mapper, bus: Bus, viz: Viz, *, from_imu: bool, ask: Bus | None = None) -> None:
        """`from_imu`: up from the bus (a replay's camera/gravity, a live accelerometer); `ask`
        (several robots): the first robot's bus, asked for its replay's camera/gravity
        (`from_first_robot`)."""
        self.mapper, self.bus, self.viz = mapper, bus, viz
        self._ask = ask
        self.found: dict | None = None  # what the IMU gave, for map_stats.json
        self._first: tuple[int, str] | None = None  # the first keyframe's stamp and optical frame
        self._first_frame: RgbdFrame | None = None
        self._live = LiveUp() if from_imu else None
        self.given = not from_imu  # up given (mapper.grid_up, a prior map): the tracker's IMU does not move it
        self._announced = False
        if self._live is None:
            if ask is None:
                self._announce()
            return
        bus.listen(ACCEL, self._on_accel)
        bus.listen(TF_STATIC, self._on_tf)

    def first_keyframe(self, frame: RgbdFrame) -> None:
        """Called before the keyframe is integrated: a replay's up for its frame applies at once."""
        if self._first is None:
            frame_id = frame.frame_id
            self._first = (frame.stamp_ns, frame_id)
            self._first_frame = frame  # to level a live camera's up on (resolve)
            # the replay serves it from before its first frame while it runs: asked here, at a fixed
            # point, a restarted mapper gets it too (a live camera serves none: its accelerometer is read)
            msg = None if self._announced else self.bus.fetch(GRAVITY, GRAVITY_WAIT_S)
            if msg is not None and msg.header.frame_id == frame_id:
                v = msg.vector  # nothing integrated yet: nothing to rebuild
                self._apply((v.x, v.y, v.z), "gravity-aligned (the replay's camera/gravity)")
                self._announce()

    def from_first_robot(self, world_from_robot: np.ndarray | None) -> None:
        """Several robots: before the first keyframe is integrated (every robot still running then
        has one waiting, so the first robot's replay is up), its up, turned into the map's world."""
        if self._announced or self._ask is None:
            return
        msg = self._ask.fetch(GRAVITY, GRAVITY_WAIT_S) if world_from_robot is not None else None
        if msg is not None:
            v = np.array([msg.vector.x, msg.vector.y, msg.vector.z], dtype=np.float64)
            up = world_from_robot[:3, :3] @ v  # type: ignore[index]
            self._apply(up, "gravity-aligned (the first robot's camera/gravity)")
        self._announce()

    def resolve(self) -> None:
        """Decide up (once, before the first grid) and announce the frame."""
        if self._announced:
            return
        assert self._live is not None
        if self._first is not None:
            try:
                up = self._live.up_at(*self._first, "the camera's accelerometer")
            except InputError as exc:  # samples, but no rest reading: level, and say why
                self.found = {"up": [float(v) for v in DEFAULT_UP], "note": f"not gravity-aligned: {exc}"}
            else:
                if up is not None:
                    up, levelled = level_on_plane(up, self._first_frame)
                    on = ", levelled on a horizontal plane of the first keyframe" if levelled else ""
                    self._apply(up, f"gravity-aligned (the live camera's accelerometer{on})")
                elif self._live.heard:  # the mapper came up after the first keyframe's samples went by
                    self.found = {"up": [float(v) for v in DEFAULT_UP],
                                  "note": "not gravity-aligned: the mapper heard no accelerometer sample near the "
                                          "first keyframe (it came up later); the first camera taken as level"}
        self._announce()

    def from_tracker(self, msg: object) -> None:
        """The tracker's IMU estimate of up in `world` (tracker/gravity), unless up was given."""
        if self.given or self._ask is not None:
            return
        v = msg.vector  # type: ignore[attr-defined]
        up = np.array([v.x, v.y, v.z], dtype=np.float64)
        on = ""
        if self._first_frame is not None:
            up, levelled = level_on_plane(up, self._first_frame)
            on = ", levelled on a horizontal plane of the first keyframe" if levelled else ""
        self.use(up, f"gravity-aligned (the tracker's IMU estimate{on})")

    def use(self, up: object, note: str) -> None:
        """Build `map` on `up` from now on, whatever was announced, and announce it."""
        self._apply(up, note)
        self._announce()

    def _apply(self, up: object, note: str) -> None:
        """Build `map` on `up` (what is integrated moves into it) and say where it came from."""
        up_t = tuple(float(v) for v in up)  # type: ignore[attr-defined]
        self.mapper.set_up(up_t)
        self.found = {"up": list(up_t), "note": note}

    def _announce(self) -> None:
        T = self.mapper.map_from_world
        self.bus.publisher(TF_STATIC).put(posemsgs.tf_msg([("map", "world", T)], 0))
        self.viz.map_frame(T)
        self._announced = True

    def _on_accel(self, msg: object) -> None:
        a = msg.linear_acceleration  # type: ignore[attr-defined]
        assert self._live is not None
        self._live.add_sample(codec.stamp_ns(msg.header), (a.x, a.y, a.z), msg.header.frame_id)  # type: ignore[attr-defined]

    def _on_tf(self, msg: object) -> None:
        assert self._live is not None
        for parent, child, T in posemsgs.tf_transforms(msg):
            self._live.add_transform(parent, child, T[:3, :3])
