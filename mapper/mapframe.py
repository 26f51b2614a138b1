"""The `map` frame (z up) of the grid: given in the config, or found from a live camera's IMU.

`octolog run` on a file finds up before the stages start (the file's accelerometer, octolog.replay.gravity)
and gives it as `mapper.grid_up`: the mapper announces `map` -> `world` at once. A live camera
(`octolog record` publishing, `--source d455`) is only read once it runs, so with `grid_up` unset
the mapper listens to `camera/accel/sample` and the camera's `/tf_static` on the bus (outside its
inbox) and decides at its first snapshot: the accelerometer's mean within 0.1 s of the first
keyframe, rotated into that keyframe's optical frame (octolog.kit.gravity). Without samples the grid
assumes a level first camera (up = -y), as before. What the IMU gave goes into map_stats.json
(`map_frame`); `octolog run` copies it into the session's config.toml, so a replay of the session
log (which carries no IMU stream to the mapper) draws the same grid.
"""

from __future__ import annotations

import dataclasses

from octolog.kit.bus import Bus
from octolog.kit.errors import InputError
from octolog.kit.gravity import LiveUp
from octolog.kit.viz import Viz
from octolog.mapper.core import Mapper, map_from_world
from octolog.mapper.grid import DEFAULT_UP
from octolog.schemas import codec
from octolog.schemas.topics import ACCEL, TF_STATIC


class MapFrame:
    """Announces `map` -> `world` on /tf_static and in Rerun, once up is known."""

    def __init__(self, mapper: Mapper, bus: Bus, viz: Viz, *, from_imu: bool) -> None:
        self.mapper, self.bus, self.viz = mapper, bus, viz
        self.found: dict | None = None  # what the IMU gave, for map_stats.json
        self._first: tuple[int, str] | None = None  # the first keyframe's stamp and optical frame
        self._live = LiveUp() if from_imu else None
        self._announced = False
        if self._live is None:
            self._announce()
            return
        bus.listen(ACCEL, self._on_accel)
        bus.listen(TF_STATIC, self._on_tf)

    def first_keyframe(self, stamp_ns: int, frame_id: str) -> None:
        if self._first is None:
            self._first = (stamp_ns, frame_id)

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
                    up_t = tuple(float(v) for v in up)
                    grid = dataclasses.replace(self.mapper.params.grid, up=up_t)
                    self.mapper.params = dataclasses.replace(self.mapper.params, grid=grid)
                    self.found = {"up": list(up_t), "note": "gravity-aligned (the live camera's accelerometer)"}
        self._announce()

    def _announce(self) -> None:
        T = map_from_world(self.mapper.params.grid)
        self.bus.publisher(TF_STATIC).put(codec.tf_msg([("map", "world", T)], 0))
        self.viz.map_frame(T)
        self._announced = True

    def _on_accel(self, msg: object) -> None:
        a = msg.linear_acceleration  # type: ignore[attr-defined]
        assert self._live is not None
        self._live.add_sample(codec.stamp_ns(msg.header), (a.x, a.y, a.z), msg.header.frame_id)  # type: ignore[attr-defined]

    def _on_tf(self, msg: object) -> None:
        assert self._live is not None
        for parent, child, T in codec.tf_transforms(msg):
            self._live.add_transform(parent, child, T[:3, :3])
