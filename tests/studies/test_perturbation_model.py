"""Issue 35: one perturbation model. The same perturbation gives the same number from simulate,
a sweep and a fit; a perturbation that cannot act is refused by each, naming the field; what a
user reads is the perturbation as configured.

Cost: one simulate program and one sweep program on the embedded clip (0.8 s window).
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from neuromotor import cli
from neuromotor.config import ConfigError, SimulationConfig
from neuromotor.config.specs import GainSetting, SweepSpec
from neuromotor.studies import record, sweep as sw
from neuromotor.studies.fit.problem import make_problem
from neuromotor.studies.simulate import load_character, prepare, run

# The push: a 40 N s impulse at the chest, ks 400, kd 20, no point (the body's COM).
IMPULSE = dict(kind="impulse", body="chest", direction=[0.0, 0.0, 1.0], magnitude=40.0, start=0.3)


def config(**hit) -> SimulationConfig:
    return SimulationConfig(duration=0.8, ks=400.0, kd=20.0, perturbations=[dict(IMPULSE, **hit)])


@pytest.fixture(scope="module")
def character():
    return load_character()


@pytest.fixture(scope="module")
def impulse_sweep(character):
    """Simulate's peaks for the chest and the right thigh, and the same two as sweep rows."""
    cfg = config()
    setup = prepare(cfg, *character)
    spec = SweepSpec([40.0], [GainSetting(400.0, 20.0)], bodies=["chest", "right_thigh"])
    rows = sw.simulate_grid(cfg, spec, setup, progress=False).rows
    single = [run(prepare(config(body=b), *character)).metrics["peak_deviation_deg"] for b in spec.bodies]
    return rows, single


def test_one_row_impulse_sweep_equals_simulate(impulse_sweep):
    rows, single = impulse_sweep
    assert single[0] > 1.0  # a real push: degrees, not the 1/h-too-small hundredths
    assert abs(rows[0]["peak_deviation_deg"] - single[0]) < 1e-10
    assert rows[0]["kind"] == "impulse" and rows[0]["duration"] == 0.0 and rows[0]["magnitude"] == 40.0


def test_a_sweep_pushes_each_body_at_its_own_com(impulse_sweep):
    rows, single = impulse_sweep
    assert rows[1]["body"] == "right_thigh"
    assert abs(rows[1]["peak_deviation_deg"] - single[1]) < 1e-10


def test_a_fit_builds_the_pulses_simulate_runs(character):
    """An impulse without a point, as a fit case: the one-step pulse at the COM, as simulate."""
    cfg = SimulationConfig(duration=0.8, perturbations=[IMPULSE, dict(IMPULSE, body="LeftElbow")])
    setup = prepare(cfg, *character)
    problem = make_problem(setup, "features")
    h, com = setup.options.h, np.asarray(setup.model.com)
    np.testing.assert_array_equal(np.asarray(problem.pulses.magnitude)[:, 0], [40.0 / h, 40.0 / h, 0.0])
    np.testing.assert_array_equal(np.asarray(problem.pulses.point)[:2, 0], np.asarray(setup.pulses.point))
    np.testing.assert_array_equal(np.asarray(problem.pulses.point)[1, 0], com[setup.model.body_names.index("LeftElbow")])
    np.testing.assert_allclose(np.asarray(problem.pulses.start)[:, 0], 0.3 - 0.5 * h, rtol=0, atol=1e-15)


@pytest.mark.parametrize("hit, driven, field", [
    (dict(body="pelvis"), [], "perturbation[0].body"),
    (dict(body="Hips"), [], "perturbation[0].body"),
    (dict(body="LeftElbow"), ["LeftElbow"], "perturbation[0].body"),
    (dict(start=0.8), [], "perturbation[0].start"),
    (dict(kind="force", start=-0.2, duration=0.1), [], "perturbation[0].start"),
])
def test_simulate_refuses_a_perturbation_that_cannot_act(character, hit, driven, field):
    cfg = SimulationConfig(duration=0.8, driven_joints=driven, perturbations=[dict(IMPULSE, **hit)])
    with pytest.raises(ConfigError, match=re.escape(f"field '{field}'")):
        prepare(cfg, *character)


@pytest.mark.parametrize("axes, field", [
    (dict(starts=[0.3, 0.8]), "sweep.starts[1]"),
    (dict(bodies=["chest", "pelvis"]), "sweep.bodies[1]"),
])
def test_every_row_of_a_sweep_is_checked_before_any_computation(character, axes, field):
    cfg = config()
    setup = prepare(cfg, *character)
    spec = SweepSpec([40.0], [GainSetting(400.0, 20.0)], **axes)
    with pytest.raises(ConfigError, match=re.escape(f"field '{field}'")):
        sw.simulate_grid(cfg, spec, setup, progress=False)


def test_cli_sweep_start_outside_the_window_exits_2(tmp_path, capsys):
    path = tmp_path / "late.toml"
    path.write_text('[sim]\nduration = 0.5\n\n[[perturbation]]\nbody = "chest"\nmagnitude = 100.0\nstart = 0.2\n\n'
                    '[sweep]\nmagnitudes = [100.0]\nks = [400.0]\nkd = [20.0]\nstarts = [0.2, 3.0]\n')
    assert cli.main(["sweep", str(path), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "field 'sweep.starts[1]' = 3 s is at or after the end of the simulated window" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


@pytest.mark.parametrize("field", ["duration = 0.1", 'shape = "square"'])
def test_an_impulse_refuses_a_duration_or_shape_it_would_ignore(tmp_path, capsys, field):
    path = tmp_path / "impulse.toml"
    path.write_text(f'[[perturbation]]\nkind = "impulse"\nbody = "chest"\nmagnitude = 10.0\n{field}\n')
    for command in ("simulate", "sweep", "fit", "experiment"):  # the one parser: each refuses it the same way
        assert cli.main([command, str(path), *(["-o", str(tmp_path / "run.npz")] if command == "simulate" else [])]) == 2
        err = capsys.readouterr().err
        key = field.split()[0]
        assert f"field 'perturbation[0].{key}' does not apply to an impulse" in err, err
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "run.npz").exists()


def test_a_window_past_the_clips_end_by_less_than_a_step_is_rounded_down(character):
    h = 1.0 / 120.0
    end = character[0].clip.duration
    setup = prepare(SimulationConfig(start=end - 2.6 * h, h=h), *character)
    assert setup.options.n_steps == 2
    assert setup.config.start + setup.options.n_steps * h <= end + 1e-12


def test_provenance_shows_the_impulse_as_configured(character):
    setup = prepare(config(magnitude=20.0), *character)
    p = record.provenance(setup)["perturbations"][0]
    assert (p["kind"], p["magnitude"], p["unit"], p["start"], p["duration"], p["shape"]) == \
        ("impulse", 20.0, "N s", 0.3, 0.0, None)
    assert np.asarray(setup.pulses.magnitude)[0] == pytest.approx(20.0 / setup.options.h)  # the step's own form


def test_plot_title_of_a_run_that_never_recovers():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from neuromotor.viz.plots import _deviation_title

    metrics = {"peak_deviation_deg": 4.5, "time_of_peak_s": 0.4, "recovery_time_s": math.nan}
    fig, ax = plt.subplots()
    title = _deviation_title(ax, {"metrics_json": np.array(json.dumps(metrics))})
    plt.close(fig)
    assert "not recovered in the window" in title and "nan" not in title


def test_figure_titles_name_an_impulse_in_newton_seconds():
    from neuromotor.studies.sweep import _gains_map_title

    spec = SweepSpec([40.0], [GainSetting(400.0, 20.0), GainSetting(100.0, 5.0)])
    assert _gains_map_title(config(), spec, "map") == "map: 40 N s impulse on chest at 0.3 s"
    assert config(kind="force").perturbations[0].label(300.0) == "300 N half_sine pulse"


def test_sweep_plot_axis_of_an_impulse_sweep_is_in_newton_seconds(impulse_sweep, tmp_path, monkeypatch):
    from neuromotor.viz import sweep_plots

    labels = []
    real = sweep_plots.save_figure
    monkeypatch.setattr(sweep_plots, "save_figure", lambda fig, *a, **k: (labels.append(fig.axes[0].get_xlabel()),
                                                                        real(fig, *a, **k))[1])
    sweep_plots.plot_sweep(impulse_sweep[0], tmp_path / "sweep.png")
    assert labels == ["impulse (N s)"]


def test_info_on_a_config_says_it_is_not_a_run_file(tmp_path, capsys):
    path = tmp_path / "run.toml"
    path.write_text('[[perturbation]]\nbody = "chest"\nmagnitude = 10.0\n')
    assert cli.main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "not a RUN.npz (not an .npz archive" in err and "pickle" not in err and len(err.strip().splitlines()) == 1
