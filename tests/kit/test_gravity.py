"""Gravity from the accelerometer (octolog.replay.source_gravity): a gravity-aligned map frame on TUM's
Kinect accelerometer and on the synthetic room's simulated IMU, and a 2D grid that does not depend
on how the camera was held at the start."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from helpers import octolog
from helpers.maps import angle_deg, z_tilt
from scipy.spatial.transform import Rotation

from octolog.kit.errors import ConfigError, InputError
from octolog.kit.up_vector import level_on_plane
from octolog.mapper.grid import grid_from_msg, map_from_world_for_up
from octolog.replay import source_gravity
from octolog.replay.sources import open_source
from octolog.replay.synthetic_trajectory import camera_trajectory


def _true_up(world_from_camera: np.ndarray) -> np.ndarray:
    """World +z (up in a z-up world: TUM's motion capture, the synthetic room) in the camera's frame."""
    return world_from_camera[:3, :3].T @ np.array([0.0, 0.0, 1.0])


def test_tum_accelerometer_axes_map_to_the_optical_frame(tmp_path: Path) -> None:
    """A Kinect lying still, camera looking 30 degrees down: the file's (ax, ay, az) in m/s² become
    up in the optical frame as (-ax, -ay, az); samples beyond 0.1 s of the frame are not used."""
    up = np.array([0.0, -math.cos(math.radians(30)), -math.sin(math.radians(30))])  # optical: y down, z forward
    a = source_gravity.KINECT_TO_OPTICAL.T @ up * source_gravity.G
    lines = ["# accelerometer data", "# timestamp ax ay az"]
    lines += [f"{100.0 + t:.4f} {a[0]:.6f} {a[1]:.6f} {a[2]:.6f}" for t in np.arange(-0.1, 0.1, 0.002)]
    lines += ["100.5000 9.8 0.0 0.0"]  # far from the frame: ignored
    (tmp_path / "accelerometer.txt").write_text("\n".join(lines) + "\n")
    got = source_gravity.tum_up(tmp_path, 100_000_000_000)
    assert angle_deg(got, up) < 0.01
    assert source_gravity.tum_up(tmp_path, 200_000_000_000) is None  # no sample near that frame
    assert source_gravity.tum_up(tmp_path / "nowhere", 100_000_000_000) is None


def test_accelerometer_in_g_not_m_s2_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "accelerometer.txt").write_text("100.0 0.0 1.0 0.0\n100.01 0.0 1.0 0.0\n")
    with pytest.raises(InputError, match=r"accelerometer.txt: the accelerometer's mean near the first frame is 1.00"):
        source_gravity.tum_up(tmp_path, 100_000_000_000)
    (tmp_path / "accelerometer.txt").write_text("100.0 0.0 x 0.0\n")
    with pytest.raises(InputError, match=r"accelerometer.txt:1: want 'timestamp ax ay az'"):
        source_gravity.tum_up(tmp_path, 100_000_000_000)


@pytest.mark.parametrize("tilt", [0.0, 30.0, -20.0])
def test_the_simulated_imu_finds_up_within_half_a_degree(tilt: float) -> None:
    src = open_source(f"synthetic:10:tilt={tilt:g}" if tilt else "synthetic:10")
    truth = _true_up(src.scene.pose(0))
    assert angle_deg(src.gravity_up(), truth) < 0.5
    if tilt:  # the tilt is in the path: frame 0 looks that much further down than the level start
        level = _true_up(open_source("synthetic:10").scene.pose(0))
        assert abs(angle_deg(truth, level) - abs(tilt)) < 0.01


def test_levelling_on_a_plane_takes_the_floor_not_a_wall() -> None:
    """Frame 0 of the room started 30 degrees down sees the floor: its normal replaces the
    accelerometer's up (0.01 degrees from the truth, against ~0.3). The level start sees walls and a
    sliver of floor: the accelerometer's up stays. An up 10 degrees off the floor's normal (a biased
    accelerometer, beyond the 5 degree window) is not levelled onto the floor."""
    tilted = open_source("synthetic:2:tilt=30")
    truth = _true_up(tilted.scene.pose(0))
    frame = next(iter(tilted.frames(0, 1)))
    up, levelled = level_on_plane(tilted.gravity_up(), frame)
    assert levelled and angle_deg(up, truth) < 0.05
    assert level_on_plane(tilted.gravity_up(), frame)[0].tobytes() == up.tobytes()  # same bytes
    level = open_source("synthetic:2")
    accel = level.gravity_up()
    up, levelled = level_on_plane(accel, next(iter(level.frames(0, 1))))
    assert not levelled and up is accel
    off = Rotation.from_rotvec([math.radians(10.0), 0.0, 0.0]).as_matrix() @ truth
    up, levelled = level_on_plane(off, frame)
    assert not levelled and up is off


def test_a_recordings_accelerometer_gives_up(tmp_path: Path) -> None:
    """`octolog record` writes the D455's accelerometer (camera/accel/sample) and where it sits
    (/tf_static); replaying the recording takes up from it, in the colour camera's frame. The
    simulated D455 filming its flat pattern (`software.scene`; the room's walk looks down a little) is
    held level: up is image-up, (0, -1, 0), within its samples' wobble."""
    out = tmp_path / "r.mcap"
    octolog("record", str(out), "--backend", "software", "--duration", "1", "--quiet",
            "--set", 'software.scene="pattern"')
    up = open_source(f"mcap:{out}").gravity_up()
    assert angle_deg(up, np.array([0.0, -1.0, 0.0])) < 2.0


def test_a_tilted_start_levels_out_after_one_second() -> None:
    t = np.array([0.0, 0.5, 1.0, 2.0])
    _, level = camera_trajectory(t)
    _, tilted = camera_trajectory(t, start_tilt_deg=30.0)
    assert angle_deg(level[0][:, 2], tilted[0][:, 2]) == pytest.approx(30.0, abs=1e-6)
    np.testing.assert_array_equal(level[2:], tilted[2:])


@pytest.mark.parametrize("spec", ["synthetic:10:tilt=x", "synthetic:10:roll=3", "synthetic:10:tilt=95",
                                  "synthetic:10:motion=spin", "synthetic:10:exposure=50", "synthetic:10:noise=tof",
                                  "synthetic:10:seed=1.5", "synthetic:10:tilt=1:tilt=2", "synthetic:10:fast",
                                  "synthetic:10:bias=0.1", "synthetic:10:noise=d455:bias=2"])
def test_bad_synthetic_options_are_refused(spec: str) -> None:
    with pytest.raises(ConfigError, match="synthetic"):
        open_source(spec)


def test_synthetic_options_build_the_scene_they_name() -> None:
    src = open_source("synthetic:10:motion=turns:exposure=8:noise=kinect:bias=0.1:seed=2")
    cfg = src.scene.config
    assert (cfg.motion, cfg.exposure_ms, cfg.depth_noise, cfg.depth_bias_px, cfg.seed) == ("turns", 8.0, "kinect", 0.1, 2)
    assert src.name == "synthetic:10:motion=turns:exposure=8:noise=kinect:bias=0.1:seed=2"
    assert open_source("synthetic").name == "synthetic:150"


def _grid_cells(session: Path) -> dict[tuple[int, int], int]:
    """Known cells of the session's last grid, keyed by their integer position in the map frame."""
    from octolog.kit.mcaplog import read_messages
    from octolog.schemas import codec
    from octolog.schemas.topics import GRID

    msgs = [m.data for m in read_messages(session / "session.mcap", [GRID.name])]
    grid = grid_from_msg(codec.decode(msgs[-1], GRID.msgtype))
    res = grid.resolution_m
    c0, r0 = round(grid.origin_xy[0] / res), round(grid.origin_xy[1] / res)
    rows, cols = np.nonzero(grid.data >= 0)
    return {(c0 + c, r0 + r): int(grid.data[r, c]) for r, c in zip(rows.tolist(), cols.tolist())}


@pytest.mark.slow
def test_the_grid_does_not_depend_on_how_the_camera_was_held_at_the_start(tmp_path: Path) -> None:
    """The synthetic room, the same 2 s path (60 frames) twice: once from a (nearly) level start, once
    starting 30 degrees further down and levelling out over its first second. With up from the
    simulated IMU, the two grids agree on 99.6 % of the cells both know (the tilted start sees some
    more floor at first: coverage differs, placement does not). The control: the tilted session's
    mapper re-run under the old assumption (up = the first camera's -y) agrees on about 40 %."""
    level, tilted, assumed = tmp_path / "level", tmp_path / "tilted", tmp_path / "assumed"
    octolog("run", "--source", "synthetic:60", "--out", str(level), "--quiet", "--rerun", "off")
    octolog("run", "--source", "synthetic:60:tilt=30", "--out", str(tilted), "--quiet", "--rerun", "off")
    octolog("replay", str(tilted), "--from", "tracker", "--set", "mapper.grid_up=[0.0,-1.0,0.0]", "--out",
            str(assumed), "--quiet", "--rerun", "off")

    def agreement(a: dict, b: dict) -> float:
        both = set(a) & set(b)
        assert len(both) > 0.6 * max(len(a), len(b))
        return sum(a[k] == b[k] for k in both) / len(both)

    ref = _grid_cells(level)
    assert agreement(ref, _grid_cells(tilted)) >= 0.98
    assert agreement(ref, _grid_cells(assumed)) < 0.8
    # and the tilted session's map frame is upright: 0.2 degrees from the room's z (measured; the
    # alignment onto the ground truth needs a path that bends: on 40 frames, nearly a straight line,
    # its rotation about the line is not pinned down)
    up = np.array(tomllib.loads((tilted / "config.toml").read_text())["mapper"]["grid_up"])
    assert z_tilt(tilted, map_from_world_for_up(up)) <= 2.0


def test_a_live_cameras_up_is_levelled_on_the_first_keyframes_floor(tmp_path: Path) -> None:
    """The mapper's live path (mapper/mapframe.py): accelerometer samples around the first keyframe
    give up within the accelerometer's error; a floor in that keyframe then levels it, as a file's
    frame 0 is levelled. A first keyframe that sees no floor keeps the accelerometer's up. A mapper
    that came up after the first keyframe's samples went by says its map is not gravity-aligned."""
    from octolog.kit.bus import Bus
    from octolog.kit.busconfig import BusConfig
    from octolog.kit.viz import Viz
    from octolog.mapper.config import MapperConfig
    from octolog.mapper.core import make_mapper
    from octolog.mapper.mapframe import MapFrame
    from octolog.schemas import sensormsgs

    def live_up(source: str, late: int = 0) -> tuple[dict, np.ndarray]:
        src = open_source(source)
        frame = next(iter(src.frames(0, 1)))
        truth = _true_up(src.scene.pose(0))
        # 2 degrees of accelerometer bias, samples at 200 Hz around the first keyframe
        biased = Rotation.from_rotvec([0.0, 0.0, math.radians(2.0)]).as_matrix() @ truth
        mapper = make_mapper(MapperConfig())
        with Bus(BusConfig(multicast_scouting=False), "mapper") as bus, Viz("off", "mapper", "t") as viz:
            live = MapFrame(mapper, bus, viz, from_imu=True)
            for k in range(-40 + late, 41 + late):
                a = tuple(float(v) for v in 9.80665 * biased)
                live._on_accel(sensormsgs.imu_msg(frame.stamp_ns + k * 5_000_000, frame.frame_id,
                                                  linear_acceleration=a))
            live.first_keyframe(frame)
            live.resolve()
        assert live.found is not None
        np.testing.assert_array_equal(mapper.map_from_world[2, :3], np.array(live.found["up"]) /
                                      np.linalg.norm(live.found["up"]))
        return live.found, truth

    found, truth = live_up("synthetic:2:tilt=30")  # looks down at the floor
    assert found["note"] == ("gravity-aligned (the live camera's accelerometer, levelled on a horizontal plane "
                             "of the first keyframe)")
    assert angle_deg(np.array(found["up"]), truth) < 0.05
    found, truth = live_up("synthetic:2")  # sees the walls
    assert found["note"] == "gravity-aligned (the live camera's accelerometer)"
    assert 1.9 < angle_deg(np.array(found["up"]), truth) < 2.1
    found, _ = live_up("synthetic:2", late=200)  # its samples from 0.8 s after the first keyframe on
    assert found["note"].startswith("not gravity-aligned: the mapper heard no accelerometer sample near the first")
