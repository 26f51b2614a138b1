"""The simulated D455's film: the synthetic room (replay/synthetic.py) seen along one known path, for
the recorder's software device (recorder/software_d455.py: FrameProvider, SimulatedLayout).

From one trajectory (replay/synthetic_trajectory.py: the walk round the pillar, or the walk with
fast head turns), per frame i at the device's stamp:

- colour: the room rendered from the colour camera's pose with its intrinsics;
- depth: the room ray-cast from the depth imager's own pose (`color_from_depth`, as the device
  registers it, so the recorder's alignment to colour is exact) with its intrinsics, read as a
  D455 would (replay/depth_noise.py's `d455`, at the depth stream's own focal length: disparity
  noise growing as z², holes along edges, dropouts; `depth_bias_px` a systematic disparity offset),
  in the device's depth units;
- IMU: gyro and accelerometer at their own rates from the path's exact motion at the IMU's place
  (`color_from_imu`; `imu_rotation_deg` turns the true IMU from it, `imu_time_offset_ms` stamps
  its samples behind the camera's clock), with the BMI085's datasheet noise and a turn-on bias per
  axis (seeded).

Rendering costs ~0.3 s a frame at 640x480 on two cores: far too much beside a live pipeline. So
frames are rendered ahead, before the camera starts (`SceneCamera.render`, with a progress line),
into a cache folder keyed by a hash of everything that decides their bytes (the layout, the
options, the renderer's source and library versions): `$OCTOLOG_SIM_CACHE`, else `simcamera` in
octolog's cache folder (octolog.kit.cache: `$OCTOLOG_CACHE`, `$XDG_CACHE_HOME/octolog`, `~/.cache/octolog`). Each frame is one file
(colour and depth as they are: 1.5 MB at 640x480), written to a temporary name and renamed, so a
killed render leaves whole frames only; frame i depends on (options, i) alone, so a longer run
renders only the frames a shorter one did not. The camera itself then reads one file a frame
(uncompressed: zstd saved a third of the disk for 3 ms of the recorder's capture thread a frame,
which doubled its CPU and cost it IMU samples on a loaded machine).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from octolog.kit import cache
from octolog.kit.errors import ConfigError
from octolog.kit.geometry import matrix_to_pose
from octolog.kit.imu import D455, GRAVITY_MS2
from octolog.recorder.config import RecorderConfig, capture_profile, make_backend
from octolog.recorder.capture import Backend
from octolog.recorder.software_d455 import SimulatedLayout, default_imu_rates, simulated_layout, stamp_ns
from octolog.replay import (
    depth_noise,
    synthetic,
    synthetic_imu,
    synthetic_room,
    synthetic_textures,
    synthetic_trajectory,
)
from octolog.replay.synthetic import SyntheticScene
from octolog.shell.statusline import StatusLine

CACHE_ENV = "OCTOLOG_SIM_CACHE"
FORMAT = 2  # the cache's layout and `_Renderer`'s recipe: bump it when either changes (a new key)
MOTIONS = {"walk": "loop", "turns": "turns"}  # SoftwareConfig.motion -> replay/synthetic_trajectory.py's
MIN_DEPTH_M, MAX_DEPTH_M = 0.4, 10.0  # nearer or farther reads 0 (a D455 at 640x480: ~0.4 m minimum)
# BMI085 datasheet: gyro noise 0.014 deg/s/√Hz and accelerometer 160 µg/√Hz (kit/imu.py: D455), zero-rate
# offset up to ±1 deg/s and zero-g offset up to ±20 mg at turn-on: each axis draws its turn-on bias
# with a third of those as one sigma
TURN_ON_GYRO_RADS = math.radians(1.0) / 3.0
TURN_ON_ACCEL_MS2 = 0.020 * GRAVITY_MS2 / 3.0
# the modules whose source keys the cache (with FORMAT)
_RENDERER = (synthetic, synthetic_room, synthetic_textures, synthetic_trajectory, depth_noise)


@dataclass(frozen=True)
class SceneOptions:
    """Everything that decides the simulated camera's bytes, but the number of frames."""

    layout: SimulatedLayout
    motion: str = "walk"
    seed: int = 0
    depth_bias_px: float = 0.0
    imu_time_offset_ms: float = 0.0
    imu_rotation_deg: float = 0.0

    def key(self) -> str:
        """A hash of what decides the frames' bytes: the options but the IMU's (computed as the camera
        runs, never cached), the renderer's source and the libraries that render."""
        lay = self.layout
        frames = {"format": FORMAT, "color": dataclasses.asdict(lay.color), "depth": dataclasses.asdict(lay.depth),
                  "fps": lay.fps, "depth_units_m": lay.depth_units_m, "color_from_depth": lay.color_from_depth,
                  "motion": self.motion, "seed": self.seed, "depth_bias_px": self.depth_bias_px}
        return cache.key_of((json.dumps(frames, sort_keys=True),), [str(m.__file__) for m in _RENDERER],
                            ("numpy", "open3d-cpu", "opencv-python-headless", "scipy"))


def cache_root() -> Path:
    """Where rendered frames are kept (see the module's docstring)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    return cache.cache_root("simcamera")


def options_for(cfg: RecorderConfig) -> SceneOptions:
    """The scene options of a recorder config (its software device's streams and `software` keys)."""
    profile = capture_profile(cfg)
    s = cfg.software
    return SceneOptions(simulated_layout(profile, *default_imu_rates(profile, s.imu_chip)), s.motion, s.seed,
                        s.depth_bias_px, s.imu_time_offset_ms, s.imu_rotation_deg)


def frames_for(cfg: RecorderConfig, duration_s: float) -> int:
    """Frames to render: `software.frames`; else the duration and a second more (the recorder stops on
    sensor time from the first frame it takes, which may come late); else one walk round the room."""
    fps = cfg.color.fps
    if cfg.software.frames:
        return cfg.software.frames
    if duration_s > 0:
        return math.ceil(duration_s * fps) + fps
    return round(synthetic_trajectory.LOOP_S * fps)


class SceneCamera:
    """The simulated D455's frames and IMU (a recorder/software_d455.py FrameProvider), read from the
    cache once `render` has filled it."""

    def __init__(self, options: SceneOptions, frames: int, root: Path | None = None) -> None:
        if frames < 1:
            raise ConfigError(f"simulated camera: {frames} frames: want at least 1")
        self.options, self.frames = options, frames
        self.folder = (root or cache_root()) / options.key()
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None

    # --- the trajectory and its ground truth -------------------------------------------------------

    @property
    def layout(self) -> SimulatedLayout:
        return self.options.layout

    def frame_time_s(self, i: int) -> float:
        return (stamp_ns(self.layout.fps, i) - stamp_ns(self.layout.fps, 0)) / 1e9

    def world_from_color(self, t: np.ndarray) -> np.ndarray:
        """The colour camera's true poses (N, 4, 4) at times t (s from frame 0)."""
        pos, rot = synthetic_trajectory.camera_trajectory(np.asarray(t, float), motion=MOTIONS[self.options.motion])
        T = np.tile(np.eye(4), (len(pos), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = rot, pos
        return T

    def groundtruth_tum(self) -> str:
        """The colour camera's true pose at every frame's stamp, TUM text (world: the room, z up)."""
        poses = self.world_from_color(np.array([self.frame_time_s(i) for i in range(self.frames)]))
        lines = ["# timestamp tx ty tz qx qy qz qw"]
        for i, T in enumerate(poses):
            ns = stamp_ns(self.layout.fps, i)
            t, q = matrix_to_pose(T)
            lines.append(f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} " + " ".join(f"{x:.9f}" for x in (*t, *q)))
        return "\n".join(lines) + "\n"

    # --- the IMU ------------------------------------------------------------------------------------

    def true_color_from_imu(self) -> np.ndarray:
        """Where the IMU really is: the calibration's place, turned by `imu_rotation_deg` about its x
        (the camera's pitch axis: the walk's yaw then leaks into the IMU's z, and its up tilts)."""
        a = math.radians(self.options.imu_rotation_deg)
        turn = np.eye(4)
        turn[:3, :3] = [[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]]
        return self.layout.color_from_imu @ turn

    def _imu_trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = self.world_from_color(t) @ self.true_color_from_imu()
        return T[:, :3, 3], T[:, :3, :3]

    @cached_property
    def _imu(self) -> dict[str, np.ndarray]:
        """Per stream, (K, 3) float32 samples from the first frame to a second past the last."""
        out = {}
        span_s = self.frame_time_s(self.frames - 1) + 1.0
        for n, (stream, rate) in enumerate((("gyro", self.layout.gyro_hz), ("accel", self.layout.accel_hz))):
            if not rate:
                out[stream] = np.zeros((0, 3), np.float32)
                continue
            k = np.arange(math.ceil(span_s * rate) + 1)
            stamps = np.array([stamp_ns(rate, int(j)) for j in k], np.int64)
            t = (stamps - stamp_ns(rate, 0)) / 1e9 + self.options.imu_time_offset_ms * 1e-3
            gyro, force = synthetic_imu.true_motion(self._imu_trajectory, t)
            truth = gyro if stream == "gyro" else force
            density, walk, turn_on = ((D455.gyro_noise, D455.gyro_walk, TURN_ON_GYRO_RADS) if stream == "gyro" else
                                      (D455.accel_noise, D455.accel_walk, TURN_ON_ACCEL_MS2))

            def draws(purpose: int, sigma: float, shape: tuple[int, ...]) -> np.ndarray:
                return np.random.default_rng([self.options.seed, 0xB085, n, purpose]).normal(0.0, sigma, shape)

            bias = draws(0, turn_on, (3,)) + np.cumsum(draws(1, walk / math.sqrt(rate), (len(k), 3)), axis=0)
            out[stream] = (truth + bias + draws(2, density * math.sqrt(rate), (len(k), 3))).astype(np.float32)
        return out

    def motion(self, stream: str, k: int) -> tuple[float, float, float]:
        samples = self._imu[stream]
        if k >= len(samples):
            raise IndexError(f"simulated {stream} sample {k}: only {len(samples)} were made")
        x, y, z = samples[k].tolist()
        return x, y, z

    # --- frames -------------------------------------------------------------------------------------

    def path(self, i: int) -> Path:
        return self.folder / f"{i:06d}.frame"

    def missing(self) -> list[int]:
        return [i for i in range(self.frames) if not self.path(i).is_file()]

    def _frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        if self._last is None or self._last[0] != i:
            if not 0 <= i < self.frames:
                raise IndexError(f"simulated frame {i}: the camera has {self.frames}")
            try:
                raw = self.path(i).read_bytes()
            except FileNotFoundError:
                raise ConfigError(f"{self.path(i)}: the simulated camera's frame {i} was not rendered "
                                  "(SceneCamera.render first)") from None
            c, d = self.layout.color, self.layout.depth
            n = c.width * c.height * 3
            colour = np.frombuffer(raw, np.uint8, n).reshape(c.height, c.width, 3)
            depth = np.frombuffer(raw, np.uint16, d.width * d.height, offset=n).reshape(d.height, d.width)
            self._last = (i, colour, depth)
        return self._last[1], self._last[2]

    def color(self, i: int) -> np.ndarray:
        return self._frame(i)[0]

    def depth(self, i: int) -> np.ndarray:
        return self._frame(i)[1]

    def for_layout(self, layout: SimulatedLayout) -> SceneCamera:
        """The software device's factory (recorder/software_d455.py: ProviderFactory): this camera,
        if it was made for the streams the device opened."""
        if layout != self.layout:
            raise ConfigError("simulated camera: the device opened other streams than the frames were rendered "
                              f"for ({layout} != {self.layout})")
        return self

    # --- rendering ----------------------------------------------------------------------------------

    def render(self, progress: Callable[[int, int], None] | None = None) -> int:
        """Render the frames the cache lacks (each written whole or not at all); how many."""
        todo = self.missing()
        if not todo:
            return 0
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / "options.json").write_text(json.dumps(dataclasses.asdict(self.options), indent=1) + "\n")
        renderer = _Renderer(self)
        for n, i in enumerate(todo):
            colour, depth = renderer.frame(i)
            tmp = self.path(i).with_suffix(f".tmp{os.getpid()}")
            tmp.write_bytes(colour.tobytes() + depth.tobytes())
            os.replace(tmp, self.path(i))
            if progress is not None:
                progress(n + 1, len(todo))
        return len(todo)


class _Renderer:
    """Colour and depth of one frame from the trajectory (the heavy part: open3d, the textures)."""

    def __init__(self, camera: SceneCamera) -> None:
        self.camera = camera
        lay, opt = camera.layout, camera.options
        c = lay.color
        self.scene = SyntheticScene(n_frames=1, width=c.width, height=c.height, fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy,
                                    seed=opt.seed)
        self.sensor = dataclasses.replace(depth_noise.SENSORS["d455"], focal_px=lay.depth.fx)
        self.color_from_depth = np.asarray(lay.color_from_depth)
        d = lay.depth
        u, v = np.meshgrid(np.arange(d.width, dtype=np.float64), np.arange(d.height, dtype=np.float64))
        self.ray_x, self.ray_y = ((u - d.cx) / d.fx).ravel(), ((v - d.cy) / d.fy).ravel()  # and z = 1
        self.dark = np.zeros((d.height, d.width, 3), np.uint8)  # the d455 model loses no dark surface

    @cached_property
    def raycaster(self) -> Any:  # open3d's RaycastingScene (Any: open3d is imported lazily)
        import open3d as o3d  # lazy: ~1.4 s to import, only rendering needs it

        verts, tris, _ = synthetic_room.scene_triangles()
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32)))
        return scene

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        import open3d as o3d  # lazy: ~1.4 s to import, only rendering needs it

        cam = self.camera
        world_from_color = cam.world_from_color(np.array([cam.frame_time_s(i)]))[0]
        colour, _ = self.scene.render_pose(world_from_color)
        T = world_from_color @ self.color_from_depth
        rays = np.empty((len(self.ray_x), 6), np.float32)
        rays[:, :3] = T[:3, 3]
        for k in range(3):  # unit z in the depth frame, so the ray parameter is z; no BLAS (as replay/synthetic.py)
            rays[:, 3 + k] = self.ray_x * T[k, 0] + self.ray_y * T[k, 1] + T[k, 2]
        z = self.raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy().astype(np.float64)
        lay = cam.layout
        z = z.reshape(lay.depth.height, lay.depth.width)
        z[~((z >= MIN_DEPTH_M) & (z <= MAX_DEPTH_M))] = 0.0
        rng = np.random.default_rng([cam.options.seed, 0xD455, i])
        read = depth_noise.apply(z, self.dark, self.sensor, rng, cam.options.depth_bias_px)
        units = np.rint(read / lay.depth_units_m)
        depth = np.where((read > 0) & (units <= 65535), units, 0).astype(np.uint16)
        return np.ascontiguousarray(colour), depth


def progress_line(label: str = "simulated D455") -> Callable[[int, int], None]:
    """A progress callback showing `label: rendered N/M frames ahead` on the status line (redrawn in
    place on a terminal, a plain line every few seconds elsewhere: shell/statusline.py)."""
    line = StatusLine()
    t0 = time.monotonic()

    def show(done: int, total: int) -> None:
        per = (time.monotonic() - t0) / max(done, 1)
        line.show(f"{label}: rendered {done}/{total} frames ahead ({per * 1e3:.0f} ms each, "
                  f"{per * (total - done):.0f} s left)")
        if done >= total:
            line.end()

    return show


def prepare(cfg: RecorderConfig, duration_s: float, *, quiet: bool = False) -> SceneCamera:
    """The simulated camera of a recorder config, every frame it will film rendered (a cold cache:
    with a progress line unless `quiet`)."""
    camera = SceneCamera(options_for(cfg), frames_for(cfg, duration_s))
    camera.render(None if quiet else progress_line())
    return camera


def backend(cfg: RecorderConfig, duration_s: float, *, quiet: bool = False) -> Backend:
    """The software D455 filming the room (rendered ahead): `octolog record --backend software`'s and
    `octolog run --source d455:software`'s camera."""
    return make_backend(cfg, prepare(cfg, duration_s, quiet=quiet).for_layout)
