"""Every shipped config in configs/ validates, and the default one is the CLI's default hit."""

import pathlib

import pytest

from neuromotor.config import DEFAULT_HIT, ConfigError, load_simulation_config, simulation_config

CONFIGS = sorted((pathlib.Path(__file__).resolve().parents[2] / "configs").glob("*.toml"))


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


def test_body_fields_are_read_checked_and_win_over_the_estimates():
    """units, up_axis, stature, body_mass, sex and simulate_extremities: read, validated with the
    field named, and the character built from them (stature with units "auto" scales the rig)."""
    import numpy as np

    from conftest import ALL_CLIPS
    from neuromotor.studies.simulate import load_character

    clip = str(ALL_CLIPS["cmu_01_01_jumps_31joint"])
    cfg = simulation_config({"clip": clip, "units": "auto", "up_axis": "auto", "stature": 1.6, "body_mass": 55.0,
                             "sex": "female", "simulate_extremities": True}, "<t>")
    assert (cfg.units, cfg.up_axis, cfg.stature, cfg.body_mass, cfg.sex, cfg.simulate_extremities) == \
        ("auto", None, 1.6, 55.0, "female", True)
    character, _ = load_character(cfg.clip, cfg.units, cfg.up_axis, cfg.stature, cfg.mass_options())
    assert character.anatomy.stature == 1.6 and character.anatomy.units == "given"
    np.testing.assert_allclose(float(np.sum(character.model.mass)), 55.0, rtol=1e-9)
    assert any(n.startswith("LeftFingerBase.") for n in character.model.dof_names)  # fingers simulated
    inches, _ = load_character(clip, "in", 2)  # explicit units and up axis win
    assert inches.clip.length_scale == 0.0254 and inches.model.gravity[2] == -9.81
    for table, field in (({"stature": -1.0}, "stature"), ({"stature": 17.0}, "stature"),
                         ({"body_mass": "heavy"}, "body_mass"), ({"sex": "x"}, "sex"),
                         ({"units": "furlong"}, "units"), ({"up_axis": 3}, "up_axis"),
                         ({"simulate_extremities": 1}, "simulate_extremities")):
        with pytest.raises(ConfigError, match=f"<t>: field '{field}'"):
            simulation_config(table, "<t>")
