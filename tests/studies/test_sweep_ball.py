"""Issue 7 in sweeps: ``neuromotor sweep`` of a [ball] config varies the ball speed.

One small sweep on the embedded clip (three speeds at the chest, a 0.5 s window, the ball
launched 0.05 s into it from 1.15 m away) through ``sweep_from_config``; its rows are checked
against physics (a faster ball hits harder and deflects more) and against a direct contact
rollout (``simulate.run``) of the same config at one of the speeds.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from neuromotor.studies import sweep as sw
from neuromotor.config import ConfigError, simulation_config
from neuromotor.studies.simulate import prepare, run

SPEEDS = [5.0, 8.0, 11.0]
CONFIG = """
[sim]
start = 0.95
duration = 0.5

[ball]
radius = 0.11
mass = 1.0
position = [-0.45, 1.4, 3.4]
speed = 8.0
target = "Chest2"
launch = 1.0
restitution = 0.6
friction = 0.5

[sweep]
magnitudes = [5.0, 8.0, 11.0]
chunk = 4
"""


@pytest.fixture(scope="module")
def ball_sweep(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ball_sweep")
    path = tmp / "ball_sweep.toml"
    path.write_text(CONFIG)
    result, files = sw.sweep_from_config(path, tmp / "out", progress=False)
    return path, result, files


def test_ball_sweep_rows_follow_the_physics(ball_sweep):
    path, result, files = ball_sweep
    rows = sw.read_csv(files["csv"])
    assert files["plot"].exists() and files["plot"].stat().st_size > 0
    assert len(rows) == len(SPEEDS)
    assert [r["magnitude"] for r in rows] == SPEEDS
    for r in rows:
        assert r["kind"] == "ball" and r["body"] == "Chest2" and r["start"] == 1.0
        assert (r["ks"], r["kd"], r["controller"]) == (400.0, 20.0, "neuromotor")
        assert not r["diverged"] and r["diverged_step"] == -1
        assert r["hit_body"] == "Chest2" and 1.0 < r["first_contact_s"] < 1.3
        assert r["max_kkt_residual"] < 1e-9 and r["max_constraint_violation"] < 1e-8
        assert r["first_contact_s"] <= r["time_of_peak_s"]
        assert all(math.isfinite(r[k]) for k in ("peak_deviation_deg", "final_error_deg", "overshoot_deg"))
    peak = np.array([r["peak_deviation_deg"] for r in rows])
    impulse = np.array([r["peak_impulse_Ns"] for r in rows])
    assert peak[0] > 0.1 and np.all(np.diff(peak) > 0)
    assert impulse[0] > 1.0 and np.all(np.diff(impulse) > 0)
    # Impulse of a hit is about (1 + e) m v_normal reduced by the chest's effective mass: below
    # (1 + e) m v, and growing roughly in proportion to the speed.
    assert np.all(impulse < 1.6 * 1.0 * np.array(SPEEDS))
    # A faster ball arrives earlier (same distance).
    first = np.array([r["first_contact_s"] for r in rows])
    assert np.all(np.diff(first) <= 0) and first[0] > first[-1]


def test_ball_sweep_row_equals_a_direct_contact_rollout(ball_sweep):
    """The middle row is `neuromotor simulate` of the config with ball.speed = 8 m/s."""
    path, result, _ = ball_sweep
    import tomllib

    data = tomllib.loads(path.read_text())
    data.pop("sweep")
    data["ball"]["speed"] = SPEEDS[1]
    res = run(prepare(simulation_config(data, str(path))))
    row = result.rows[1]
    m = res.metrics
    for k in ("peak_deviation_deg", "time_of_peak_s", "final_error_deg", "overshoot_deg"):
        assert abs(row[k] - m[k]) <= 1e-9, (k, row[k], m[k])
    assert (math.isnan(row["recovery_time_s"]) and math.isnan(m["recovery_time_s"])) or \
        abs(row["recovery_time_s"] - m["recovery_time_s"]) <= 1e-9
    # Peak impulse on the character: the contact record without the ground candidate.
    imp = np.linalg.norm(np.asarray(res.ball.contact.impulse), axis=-1)[:, :-1]
    assert abs(row["peak_impulse_Ns"] - imp.max()) <= 1e-9 * max(1.0, imp.max())


def test_ball_sweep_config_errors_name_the_field(tmp_path):
    base = CONFIG.replace("[sweep]", "[sweep]\nstarts = [1.0]")
    path = tmp_path / "bad.toml"
    path.write_text(base)
    with pytest.raises(ConfigError, match=r"field 'sweep\.starts' does not apply to a ball sweep"):
        sw.load_sweep_config(path)
    path.write_text(CONFIG + '\n[[perturbation]]\nbody = "Chest2"\nmagnitude = 100.0\n')
    with pytest.raises(ConfigError, match=r"field 'perturbation': a sweep of a \[ball\] config"):
        sw.load_sweep_config(path)
    path.write_text(CONFIG.replace("[5.0, 8.0, 11.0]", "[0.0, 8.0]"))
    with pytest.raises(ConfigError, match=r"field 'sweep\.magnitudes' ball speeds must be > 0"):
        sw.load_sweep_config(path)
    cfg, spec = sw.load_sweep_config(pathlib.Path(__file__).resolve().parents[2] / "configs" / "sweep_ball_speed.toml")
    assert spec.kind == "ball" and spec.magnitudes == [4.0, 8.0, 12.0, 16.0] and cfg.ball["target"] == "Chest2"
