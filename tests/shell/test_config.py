from __future__ import annotations

import dataclasses
import tomllib

import pytest

from octolog.kit.config import load, to_json
from octolog.kit.errors import ConfigError
from octolog.mapper.config import MapperConfig
from octolog.mapper.sensor_model import SensorModel
from octolog.replay.config import ReplayConfig
from octolog.tracker.config import TrackerConfig


def test_defaults_and_overrides(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('[tracker]\nn_features = 800\n[mapper]\nresolution_m = 0.1\n')
    assert load(TrackerConfig, f, section="tracker").n_features == 800
    cfg = load(MapperConfig, f, ["voxel_m=0.02", "sor_first=true"], section="mapper")
    assert (cfg.resolution_m, cfg.voxel_m, cfg.sor_first) == (0.1, 0.02, True)
    assert load(ReplayConfig, None, ['wait_for=["tracker", "mapper"]']).wait_for == ("tracker", "mapper")


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        (["n_feature=5"], "unknown config key 'n_feature'"),
        (["n_features=many"], "'n_features'"),
        (["n_features=50"], "tracker.n_features 50"),
        (["n_features"], "want key=value"),
    ],
)
def test_bad_keys_and_values_name_the_key(overrides, fragment):
    with pytest.raises(ConfigError, match=fragment):
        load(TrackerConfig, None, overrides)


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load(TrackerConfig, tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[tracker\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load(TrackerConfig, bad)


def test_resolved_config_is_canonical():
    assert to_json(MapperConfig()) == to_json(load(MapperConfig, None, []))
    assert '"resolution_m": 0.05' in to_json(MapperConfig())


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        (["prob_hit=1.5"], "mapper.prob_hit must be a probability in \\(0, 1\\)"),
        (["prob_hit=0.45"], "prob_miss < occupancy_thres < prob_hit"),
        (["clamp_max=0.4"], "clamp_min < occupancy_thres < clamp_max"),
        (["sor_neighbors=0"], "mapper.sor_neighbors 0"),
        (["grid_resolution_m=0"], "mapper.grid_resolution_m 0"),
    ],
)
def test_mapper_config_checks_every_value_once(overrides, fragment):
    with pytest.raises(ConfigError, match=fragment):
        load(MapperConfig, None, overrides)
    with pytest.raises(ConfigError, match=fragment):  # params() validates a config built in code too
        dataclasses.replace(MapperConfig(), **{k: tomllib.loads(f"v = {v}")["v"]
                                               for k, v in (o.split("=") for o in overrides)}).params()


def test_mapper_params_group_the_config_and_keep_octomaps_defaults_but_the_top_clamp():
    p = load(MapperConfig, None, ["prob_hit=0.8", "voxel_m=0.02", "grid_z_max_m=0.5", "backend=octomap"]).params()
    assert p.occupancy.sensor == SensorModel(prob_hit=0.8, clamp_max=0.9)
    assert (p.occupancy.backend, p.cloud.voxel_m, p.grid.z_max_m, p.max_extent_m) == ("octomap", 0.02, 0.5, 1000.0)
    assert SensorModel() == SensorModel(0.7, 0.4, 0.12, 0.97, 0.5)  # OctoMap's
    assert MapperConfig().params().occupancy.sensor == SensorModel(clamp_max=0.9)  # people walk through
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.cloud.voxel_m = 0.5  # type: ignore[misc]


def test_a_live_session_runs_the_camera_at_640x480_unless_told(tmp_path):
    """`octolog run` with a live source: colour and depth at 640x480 (what the pipeline keeps up with
    on two cores at 30 fps), unless --set or the config file names a stream's size."""
    from octolog.recorder.config import RecorderConfig
    from octolog.shell.run import _live_resolution

    rec = RecorderConfig()
    assert (rec.color.width, rec.color.height) == (1280, 720)  # recording alone keeps its own default
    live = _live_resolution(rec, None, [])
    assert (live.color.width, live.color.height, live.depth.width, live.depth.height) == (640, 480, 640, 480)
    assert live.color.fps == rec.color.fps
    told = _live_resolution(rec, None, ["color.width=848", "color.height=480"])
    assert (told.color.width, told.depth.width) == (1280, 640)  # the given stream is left as loaded
    cfg = tmp_path / "c.toml"
    cfg.write_text("[recorder.depth]\nwidth = 848\nheight = 480\n")
    from_file = _live_resolution(rec, str(cfg), [])
    assert (from_file.color.width, from_file.depth.width) == (640, rec.depth.width)


def test_set_takes_the_section_form_everywhere(capsys):
    """`--set tracker.n_features=800`, the form `octolog run` takes, works for `track` too (and the
    bare `n_features=800`); another stage's key says which forms this command takes."""
    from octolog.kit.config import load
    from octolog.shell import cli
    from octolog.tracker.config import TrackerConfig

    assert load(TrackerConfig, None, ["tracker.n_features=800"], section="tracker").n_features == 800
    assert load(TrackerConfig, None, ["n_features=700"], section="tracker").n_features == 700
    assert cli.main(["track", "--set", "mapper.voxel_m=0.1"]) == 1
    assert capsys.readouterr().err == ("octolog track: error: --set 'mapper.voxel_m=0.1': this command takes "
                                       "[tracker] keys: --set KEY=VALUE or --set tracker.KEY=VALUE\n")


def test_a_stage_commands_config_file_without_its_section_is_the_wrong_file(tmp_path, capsys):
    """`record --config` of a file with [tracker] alone is refused in one line naming the sections it
    has; `run` reads such a file (each stage its own section, defaults for the others)."""
    from octolog.kit.config import load
    from octolog.recorder.config import RecorderConfig
    from octolog.shell import cli

    f = tmp_path / "t.toml"
    f.write_text("[tracker]\nn_features = 800\n")
    assert load(RecorderConfig, f, section="recorder") == RecorderConfig()  # run's reading: defaults
    assert cli.main(["record", str(tmp_path / "x.mcap"), "--config", str(f)]) == 1
    assert capsys.readouterr().err == (f"octolog record: error: {f}: no [recorder] section (it has [tracker]); "
                                       "this command reads [recorder]\n")
    assert not (tmp_path / "x.mcap").exists()
