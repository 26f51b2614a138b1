from __future__ import annotations

import pytest

from octolog.kit.config import load, to_json
from octolog.kit.errors import ConfigError
from octolog.mapper.config import MapperConfig
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
