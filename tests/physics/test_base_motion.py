"""Issue 37: a base motion (a sled, a vehicle, a platform) adds a prescribed acceleration to the
driven root's path. Physics: a base-motion run is the unperturbed frame's run under the inertial
forces -m_b a on every body (to round-off); the added velocity and displacement are the exact
integrals of the pulse or the recorded series; the feedforward is the capture's.

Cost: three short programs on the embedded clip (0.25 s at h = 1/240 s).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.config import ConfigError, SimulationConfig
from neuromotor.config.parse import simulation_config
from neuromotor.physics import solvers
from neuromotor.physics.dynamics import Data, Params, StepInfo, equations_of_motion, integrate, simulate
from neuromotor.physics.perturbation import STANDARD_GRAVITY, base_motion, profile_integral, series_integral
from neuromotor.studies.simulate import load_character, prepare, run

H = 1.0 / 240.0
SLED = dict(kind="base", direction="backward", magnitude=15.0, unit="g", shape="half_sine", duration=0.1, start=0.85)


def config(*perts, **sim) -> SimulationConfig:
    sim = {"start": 0.8, "duration": 0.25, "h": H, **sim}
    return simulation_config({"sim": sim, "gains": {"ks": 400.0, "kd": 20.0}, "perturbation": list(perts)}, "t.toml")


@pytest.fixture(scope="module")
def character():
    return load_character()


@pytest.fixture(scope="module")
def sled(character):
    setup = prepare(config(SLED, driven_joints=["Chest"]), *character)
    return setup, run(setup)


def test_velocity_and_displacement_are_the_exact_integrals():
    t = np.linspace(0.0, 0.3, 301)
    spec = dict(SLED, start=0.1)
    v, d = base_motion([spec], t, 1e-3, lambda value, time: np.array([0.0, 0.0, -1.0]))
    dv = 15.0 * STANDARD_GRAVITY * 0.1 * 2 / np.pi  # half-sine: peak * duration * 2 / pi
    assert abs(v[-1, 2] + dv) < 1e-12 * dv and np.all(v[:101] == 0.0)
    assert np.allclose(d[1:] - d[:-1], 1e-3 * v[1:], rtol=0, atol=1e-15) and np.all(d[0] == 0)
    # Phase integrals of the unit profiles, against quadrature.
    s = np.linspace(0, 1, 200001)
    for shape, f in (("square", np.ones_like(s)), ("half_sine", np.sin(np.pi * s)), ("triangle", 1 - abs(2 * s - 1))):
        quad = np.concatenate([[0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(s))])
        assert np.max(abs(profile_integral(shape, s) - quad)) < 1e-9
    # A piecewise linear series is integrated exactly, and is zero outside its samples.
    tr, ar = np.array([0.0, 0.02, 0.05, 0.07]), np.array([0.0, 3.0, -1.0, 2.0])
    tt = np.array([-1.0, 0.01, 0.02, 0.035, 0.07, 1.0])
    exact = [0, 0.5 * 0.01 * 1.5, 0.03, 0.03 + 0.015 * 3 - 0.5 * 0.015**2 * 4 / 0.03, 0.03 + 0.03 + 0.01, 0.07]
    assert np.allclose(series_integral(tr, ar, tt), exact, rtol=0, atol=1e-15)


def test_a_recorded_triangle_equals_the_triangle_pulse(character, sled, tmp_path):
    """The same acceleration given as samples and as a shape: the same run to round-off."""
    csv = tmp_path / "t1.csv"
    csv.write_text("# a 15 g triangle, 100 ms\ntime,acc\n0,0\n50,15\n100,0\n")
    rec = dict(kind="base", direction="backward", unit="g", file=str(csv), time_unit="ms", start=0.85)
    a = prepare(config(rec, driven_joints=["Chest"]), *character)
    b = prepare(config(dict(SLED, shape="triangle"), driven_joints=["Chest"]), *character)
    ra, rb = simulate(a.sim_model, a.params), simulate(b.sim_model, b.params)
    assert float(jnp.max(jnp.abs(a.pulses.base_velocity - b.pulses.base_velocity))) < 1e-12
    assert float(jnp.max(jnp.abs(ra.states.pos - rb.states.pos))) < 1e-10
    assert float(jnp.max(jnp.abs(ra.states.pos - sled[1].unperturbed.states.pos))) > 0.1  # it moved


def _inertial_step(acc, mass):
    """The ordinary step with the forces -m_b acc_k added to every body (no base motion)."""

    def step(sim, params, data):
        cfg, solver = sim.options, solvers.get(sim.options.solver)
        eq = equations_of_motion(sim, params, data, solver)
        r = eq.r.at[:, :3].add(-cfg.h * mass[:, None] * acc[data.k])
        v_new, aux = solver.solve(eq.system, r, eq.b)
        lam, residual = solver.multipliers(eq.system, r, eq.b, v_new, aux)
        new, violation = integrate(sim, solver, data.k, data.state, cfg.h * v_new, v_new, params.pulses)
        info = StepInfo(residual, violation, eq.force, eq.points, lam / cfg.h, eq.reflex)
        return Data(data.k + 1, new, info, eq.history)

    return step


def test_base_motion_equals_inertial_forces_in_the_moving_frame(sled):
    """Physics: in the frame that moves with the base the run is the unperturbed frame's under
    -m_b a_k on every body, a_k = (V_k+1 - V_k) / h the base's mean acceleration over step k."""
    from neuromotor.physics.dynamics import init_data, rollout_of, scan_steps

    setup, result = sled
    p = setup.pulses
    V, D = p.base_velocity, p.base_offset
    acc = (V[1:] - V[:-1]) / setup.options.h
    still = dataclasses.replace(p, base_velocity=None, base_offset=None)
    params = Params(setup.gains, still)
    sim = setup.sim_model
    data0 = init_data(sim, params)
    out = rollout_of(sim, data0, *scan_steps(sim, params, data0, _inertial_step(acc, setup.model.mass)))
    moved = result.perturbed.states
    assert float(jnp.max(jnp.abs(V))) > 9.0  # a 15 g, 100 ms pulse: 9.4 m/s
    pos_err = float(jnp.max(jnp.abs(moved.pos - D[:, None] - out.states.pos)))
    vel_err = float(jnp.max(jnp.abs(moved.vel - V[:, None] - out.states.vel)))
    quat_err = float(jnp.max(jnp.abs(moved.quat - out.states.quat)))
    assert pos_err < 1e-11 and vel_err < 1e-9 and quat_err < 1e-11, (pos_err, vel_err, quat_err)
    # and the response is real: the free joints swing by degrees
    assert result.metrics["peak_deviation_deg"] > 5.0


def test_the_feedforward_is_the_captures(sled, character):
    """The person does not anticipate the jolt: the reference (feedforward, targets) is the
    unperturbed setup's; only the root's path moves, rigidly with every driven body."""
    setup, result = sled
    plain = prepare(config(driven_joints=["Chest"]), *character)
    assert np.array_equal(np.asarray(setup.ref.tau), np.asarray(plain.ref.tau))
    pert, base = result.perturbed.states, result.unperturbed.states
    D = np.asarray(setup.pulses.base_offset)
    for b in (0, setup.model.body_names.index("Chest")):  # the root and a driven joint's body move with the base
        err = np.asarray(pert.pos[:, b]) - np.asarray(base.pos[:, b]) - D
        assert np.max(np.abs(err)) < 1e-9
    assert result.metrics["unperturbed_rms_error_deg"] < 1e-9


def test_keyword_direction_is_the_characters_backward(sled):
    from neuromotor.model.facing import character_axes

    setup, _ = sled
    V = np.asarray(setup.pulses.base_velocity)[-1]
    back = character_axes(setup.character, 0.85)["backward"]
    assert np.allclose(V / np.linalg.norm(V), back, atol=1e-12)
    assert abs(back @ np.asarray(setup.character.anatomy.up)) < 1e-12


@pytest.mark.parametrize(
    ("table", "message"),
    [
        (dict(SLED, unit=None), "field 'perturbation[0].unit' is required for kind = 'base'"),
        (dict(SLED, unit="G"), "field 'perturbation[0].unit' must be one of ['g', 'm/s^2']"),
        (dict(SLED, direction="behind"), "field 'perturbation[0].direction' must be 3 numbers or one of"),
        (dict(SLED, body="chest"), "field 'perturbation[0].body' does not apply to a base"),
        (dict(SLED, magnitude=None), "field 'perturbation[0].magnitude' is required for a base pulse"),
        (dict(kind="force", body="chest", magnitude=1.0, unit="g"), "'perturbation[0].unit' does not apply to a force"),
        (dict(kind="force", body="chest", magnitude=1.0, file="a.csv"), "'perturbation[0].file' does not apply"),
        (dict(SLED, tilt=5.0), "field 'perturbation[0].tilt' is not read by a base motion, which translates"),
    ],
)
def test_config_errors_name_the_field(table, message):
    table = {k: v for k, v in table.items() if v is not None}
    with pytest.raises(ConfigError) as e:
        config(table)
    assert message in str(e.value), str(e.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("t,acc\n0,1\n1,2\n", "line 1: no 'time' column"),
        ("time,acc\n0,1\n2,2\n1,3\n", "line 4: time 1 is not after the previous row's"),
        ("time,acc\n0,1\n0.5,x\n", "line 3: not a number"),
        ("time,acc\n0,1\n", "needs at least 2 rows"),
        ("time,acc,more\n0,1,2\n", "the header must name 'time' and one acceleration column"),
    ],
)
def test_csv_errors_name_the_file_and_line(tmp_path, text, message):
    csv = tmp_path / "acc.csv"
    csv.write_text(text)
    rec = dict(kind="base", direction="backward", unit="g", file=str(csv), start=0.85)
    with pytest.raises(ConfigError) as e:
        config(rec)
    assert "field 'perturbation[0].file'" in str(e.value) and message in str(e.value), str(e.value)
    with pytest.raises(ConfigError, match="does not apply to a recorded base motion"):
        config(dict(rec, shape="square"))


def test_the_record_shows_the_directions_the_run_used(character):
    """RUN.npz's provenance gives each perturbation's world direction as built, a held pose's
    keywords in that pose's frame (backward and left at right angles)."""
    from neuromotor.studies.record import _perturbation_records

    still = character[0].anatomy.reference_frame * character[0].clip.frame_time
    push = dict(kind="impulse", body="head", direction="left", magnitude=2.0, start=0.1)
    setup = prepare(config(dict(SLED, start=0.05), push, still=still, start=0.0, duration=0.2), *character)
    base, imp = _perturbation_records(setup)
    V = np.asarray(setup.pulses.base_velocity)[-1]
    assert np.allclose(base["direction"], V / np.linalg.norm(V), atol=1e-12)
    assert np.allclose(imp["direction"], np.asarray(setup.pulses.direction)[0], atol=1e-12)
    assert abs(np.dot(base["direction"], imp["direction"])) < 1e-12
    assert base["direction_given"] == "backward" and imp["body"] == "Head"
