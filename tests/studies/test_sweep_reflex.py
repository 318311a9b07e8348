"""Issue 18: the reflex gain and delay as sweep axes. A 2 x 2 grid (gain x delay) on the 4-body
clip equals single runs with those reflex settings, each against a twin with the same reflex;
the [sweep] reflex axes parse into the grid (history extended to the longest delay) and bad
ones give a one-line ConfigError naming the field.

Two compiles: the sweep program and the single-run program, on the small clip."""

from __future__ import annotations

import numpy as np
import pytest

from neuromotor.config import ConfigError, SimulationConfig, simulation_config
from neuromotor.config.parse import sweep_spec
from neuromotor.config.specs import ReflexSpec, reflex_grid
from neuromotor.studies import metrics as mx
from neuromotor.studies import sweep as sw
from neuromotor.studies.simulate import body_lookup, load_character, prepare, run
from test_sweep import tiny_bvh

GAINS = [100.0, 300.0]
DELAYS = [0.02, 0.07]
HIT = dict(kind="force", body="Forearm", point=[0.1, 0.0, 0.0], direction=[0.0, 0.0, 1.0], magnitude=20.0,
           start=0.2, duration=0.1, shape="half_sine")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return load_character(tiny_bvh(tmp_path_factory.mktemp("tiny") / "tiny.bvh"))


def _config(rx: ReflexSpec) -> SimulationConfig:
    return SimulationConfig(duration=0.5, perturbations=[HIT], reflex=rx)


@pytest.fixture(scope="module")
def grid(clip):
    s = prepare(_config(ReflexSpec()), *clip)
    spec = sw.SweepSpec([HIT["magnitude"]], [sw.GainSetting(400.0, 20.0)], chunk=4,
                        reflexes=reflex_grid(ReflexSpec(), reflex_gain=GAINS, reflex_delay=DELAYS))
    sweeper = sw.Sweeper(s.model, s.ref, s.options, chunk=4, inner_batch=1)
    result = sw.run_sweep(sweeper, s.gains, s.pulses, spec.runs(HIT), body_lookup(s.model), s.model.body_names,
                          keep_curves=True, progress=False)
    return spec, result


def test_grid_rows_equal_single_runs_with_their_reflex(grid, clip):
    _, result = grid
    assert [(r["reflex_gain"], r["reflex_delay"]) for r in result.rows] == [(g, d) for g in GAINS for d in DELAYS]
    for i, row in enumerate(result.rows):
        one = run(prepare(_config(ReflexSpec(gain=row["reflex_gain"], delay=row["reflex_delay"])), *clip))
        curve = np.asarray(mx.joint_deviation(clip[0].model, one.perturbed.states.quat, one.unperturbed.states.quat))
        np.testing.assert_allclose(result.curves[i], curve, rtol=0, atol=1e-10)
        for k in ("peak_deviation_deg", "time_of_peak_s", "overshoot_deg", "final_error_deg"):
            np.testing.assert_allclose(row[k], one.metrics[k], rtol=1e-9, atol=1e-12, err_msg=k)
        assert not row["diverged"]
    # Not trivially equal: the reflex setting changes the response (gain and delay both matter).
    c = result.curves
    assert np.abs(c[0] - c[2]).max() > 1e-3 and np.abs(c[0] - c[1]).max() > 1e-3


def test_reflex_columns_in_the_table_and_the_map(grid, tmp_path):
    spec, result = grid
    cfg = _config(ReflexSpec())
    files = sw.write_outputs(cfg, spec, result, tmp_path, "reflex grid")
    back = sw.read_csv(files["csv"])
    for a, b in zip(back, result.rows):
        for k in sw.REFLEX_COLUMNS:
            assert a[k] == b[k], k
    assert {r["long_latency_gain"] for r in back} == {0.0}
    assert files["reflex_map"].stat().st_size > 5000 and "gains_map" not in files


def _spec(sweep: dict, reflex: dict | None = None, ball: bool = False):
    data = {"sweep": sweep, **({"reflex": reflex} if reflex is not None else {})}
    if ball:
        data["ball"] = {"position": [0.0, 1.2, 3.0], "velocity": [0.0, 0.0, -5.0]}
    else:
        data["perturbation"] = [dict(HIT)]
    cfg = simulation_config(data, "cfg.toml")
    return cfg, sweep_spec(data, cfg)


def test_reflex_axes_parse_into_the_grid():
    cfg, spec = _spec({"reflex_gain": {"start": 0.0, "stop": 200.0, "num": 3}, "reflex_delay": [0.01, 0.3],
                       "long_latency_gain": [5.0]}, {"one_sided": True})
    assert [(r.gain, r.delay, r.long_latency_gain) for r in spec.reflexes] == [
        (g, d, 5.0) for g in (0.0, 100.0, 200.0) for d in (0.01, 0.3)]
    # One static history for the batch: every setting holds the grid's longest delay (0.3 s > the default).
    assert {r.max_delay for r in spec.reflexes} == {0.3} and all(r.one_sided for r in spec.reflexes)
    runs = spec.runs(cfg.perturbations[0])
    assert len(runs) == 6 and runs[3]["reflex"] == spec.reflexes[3]
    assert sweep_spec({"sweep": {}, "perturbation": [HIT]}, cfg).reflexes is None  # no axes: the config's reflex


@pytest.mark.parametrize("sweep, reflex, ball, field", [
    ({"reflex_gain": [100.0]}, None, False, "sweep.reflex_gain"),           # no [reflex] table
    ({"long_latency_delay": [0.05]}, None, False, "sweep.long_latency_delay"),
    ({"reflex_delay": [0.02, 1.5]}, {}, False, "sweep.reflex_delay"),       # beyond the 1 s history
    ({"reflex_gain": [-1.0]}, {}, False, "sweep.reflex_gain"),
    ({"reflex_gain": [100.0]}, {}, True, "sweep.reflex_gain"),              # ball sweeps vary the speed
])
def test_bad_reflex_axes_name_the_field(sweep, reflex, ball, field):
    with pytest.raises(ConfigError) as e:
        _spec(sweep, reflex, ball)
    msg = str(e.value)
    assert f"'{field}'" in msg and "\n" not in msg and msg.startswith("cfg.toml")
