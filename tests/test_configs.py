"""Every shipped config in configs/ validates, and the default one is the CLI's default hit."""

import pathlib

import pytest

from neuromotor.config import DEFAULT_HIT, ConfigError, load_simulation_config, simulation_config

CONFIGS = sorted((pathlib.Path(__file__).resolve().parents[1] / "configs").glob("*.toml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_shipped_config_validates(path):
    cfg = load_simulation_config(path)
    if cfg.clip is not None:
        assert pathlib.Path(cfg.clip).exists(), cfg.clip


def test_default_config_is_the_default_hit():
    cfg = load_simulation_config(CONFIGS[0].parent / "simulate_default.toml")
    assert cfg.perturbations == [DEFAULT_HIT]
    assert cfg.duration == 3.0


def test_unknown_table_and_bad_values_name_the_field(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[sim]\nh = -0.01\n")
    with pytest.raises(ConfigError, match=r"bad\.toml: field 'sim\.h' must be > 0"):
        load_simulation_config(bad)
    with pytest.raises(ConfigError, match=r"field 'simulation' is not a known field"):
        simulation_config({"simulation": {}}, "x.toml")
    bad.write_text("[sim\nh = 1\n")
    with pytest.raises(ConfigError, match=r"bad\.toml: invalid TOML"):
        load_simulation_config(bad)


def test_stabilization_steps_is_read_and_checked():
    assert simulation_config({}, "x.toml").stabilization_steps == 2
    assert simulation_config({"sim": {"stabilization_steps": 1}}, "x.toml").stabilization_steps == 1
    for bad in (0, 6, 1.5, True, "2"):
        with pytest.raises(ConfigError, match=r"x\.toml: field 'sim\.stabilization_steps' must be an integer from 1 to 5"):
            simulation_config({"sim": {"stabilization_steps": bad}}, "x.toml")
