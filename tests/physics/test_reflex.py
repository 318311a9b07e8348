"""The delayed stretch reflex (physics/reflex.py): the interpolated delay line, the one-sided
stretch signal, zero delay against the undelayed feedback term, the impulse response (the reflex
answers exactly ``delay`` after the hit reaches the joints), gradients with respect to gain and
delay against central differences, and a reflex of zero gain reproducing the paper's run."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.config import ConfigError, SimulationConfig, simulation_config
from neuromotor.physics.control import joint_torques
from neuromotor.physics.dynamics import Params, SimModel, delayed_reflex, reference_inputs, rollout
from neuromotor.physics.reflex import delayed, empty_history, make_reflex, stretch
from neuromotor.physics.system import State
from neuromotor.rotations import quat_mul
from neuromotor.studies import fit as F
from neuromotor.studies.simulate import load_character, prepare

jax.config.update("jax_enable_x64", True)

H = 1.0 / 120.0


@pytest.fixture(scope="module")
def setup():
    character, traj = load_character(CLIPS["mocapbank"])
    push = dict(kind="force", body="chest", point=[0.0, 0.1, 0.0], direction=[0.0, 0.0, 1.0], magnitude=300.0,
                start=0.9 + 3 * H, duration=0.05, shape="square")
    return prepare(SimulationConfig(start=0.9, duration=0.25, perturbations=[push]), character, traj)


def test_delay_line_interpolates_linearly():
    """A signal linear in the lag is read back exactly at any delay, clamped past the buffer."""
    lag = jnp.arange(8.0)[:, None, None] * jnp.ones((1, 2, 3))
    buf = 0.3 - 0.25 * lag
    for d in (0.0, 1.0 * H, 2.37 * H, 5.5 * H):
        np.testing.assert_allclose(delayed(buf, jnp.asarray(d), H), 0.3 - 0.25 * d / H, rtol=0, atol=1e-14)
    np.testing.assert_allclose(delayed(buf, jnp.asarray(20 * H), H), buf[-1], atol=1e-14)
    g = jax.grad(lambda d: jnp.sum(delayed(buf, d, H)))(jnp.asarray(2.37 * H))
    np.testing.assert_allclose(g, 6 * (-0.25 / H), rtol=1e-12)


def test_one_sided_stretch_acts_only_on_the_loaded_muscle():
    ref = jnp.ones(3)
    two = make_reflex(H, rate_weight=0.0)
    one = dataclasses.replace(two, one_sided=jnp.asarray(1.0))
    u = jnp.array([-0.2, 0.05, 0.2])
    np.testing.assert_array_equal(stretch(two, u, 0 * u, 5 * ref, ref), u)
    # Positive feedforward torque: the loaded muscle is stretched by positive errors only.
    pos = stretch(one, u, 0 * u, 5 * ref, ref)
    np.testing.assert_allclose(pos, [0.0, 0.05, 0.2], atol=1e-5)  # the ramp is 10 widths from its knee
    # Negative torque: the antagonist is loaded, the signs swap.
    neg = stretch(one, -u, 0 * u, -5 * ref, ref)
    np.testing.assert_allclose(neg, [0.0, -0.05, -0.2], atol=1e-5)
    assert np.all(np.isfinite(jax.grad(lambda x: jnp.sum(stretch(one, x, 0 * x, 5 * ref, ref)))(u)))


def _off_reference_state(s):
    """The first state turned and spun away from the mocap (every joint has an error)."""
    st = s.ref.init
    rng = np.random.default_rng(3)
    n = st.quat.shape[0]
    turn = jnp.concatenate([jnp.ones((n, 1)), 0.05 * jnp.asarray(rng.standard_normal((n, 3)))], -1)
    quat = quat_mul(st.quat, turn / jnp.linalg.norm(turn, axis=-1, keepdims=True))
    return State(st.pos, quat, st.vel, st.omega + 0.5 * jnp.asarray(rng.standard_normal((n, 3))))


def test_zero_delay_is_the_undelayed_feedback_term(setup):
    """Delay 0, two-sided: the reflex is the muscle feedback term of Section 5.2 with ks = g and
    kd = g c, evaluated explicitly (without feedforward)."""
    s = setup
    g, c = 250.0, 0.07
    gains = dataclasses.replace(s.gains, reflex=make_reflex(H, gain=g, delay=0.0, rate_weight=c))
    sim = SimModel(s.model, s.ref, s.options)
    state = _off_reference_state(s)

    @jax.jit
    def both(gains, state):
        inputs = reference_inputs(sim, gains, 4)
        history = empty_history(gains.reflex, s.model.n_bodies - 1, state.pos.dtype)
        torque, _, _ = delayed_reflex(sim, gains, inputs, state, history)
        fb = dataclasses.replace(gains, ks=jnp.asarray(g), kd=jnp.asarray(g * c), feedforward=jnp.asarray(0.0))
        return torque, joint_torques(s.model, fb, inputs, state.rot, state.omega)

    reflex, feedback = both(gains, state)
    assert float(jnp.max(jnp.abs(feedback))) > 1.0  # a real test: the errors are not small
    np.testing.assert_allclose(reflex, feedback, rtol=0, atol=1e-11 * float(jnp.max(jnp.abs(feedback))))


def _with_spinal(gains, g, d):
    """``gains`` with the spinal path at gain g and delay d (the long-latency path off)."""
    rx = gains.reflex
    rx = dataclasses.replace(rx, spinal=dataclasses.replace(rx.spinal, gain=g, delay=d),
                             long_latency=dataclasses.replace(rx.long_latency, gain=0.0 * g))
    return dataclasses.replace(gains, reflex=rx)


@pytest.fixture(scope="module")
def batch(setup):
    """Rollouts over 4 (gain, delay) pairs x 2 pulse magnitudes (the hit and none), one program."""
    s = setup
    base = dataclasses.replace(s.gains, reflex=make_reflex(H))

    def one(g, d, mag):
        pulses = dataclasses.replace(s.pulses, magnitude=mag)
        return rollout(s.model, _with_spinal(base, g, d), pulses, s.ref, s.options)

    run = jax.jit(jax.vmap(jax.vmap(one, (None, None, 0)), (0, 0, None)))
    mags = jnp.stack([s.pulses.magnitude, jnp.zeros_like(s.pulses.magnitude)])
    return lambda gains, delays: run(jnp.asarray(gains), jnp.asarray(delays), mags)


@pytest.fixture(scope="module")
def impulse_runs(batch):
    """Perturbed and unperturbed twins at an integer and a half-step delay, and at zero gain."""
    m = 5
    return m, batch([300.0, 300.0, 0.0, 100.0], [m * H, (m + 0.5) * H, m * H, m * H])


def test_reflex_answers_exactly_delay_after_the_hit(impulse_runs):
    m, runs = impulse_runs
    assert np.all(np.asarray(runs.diverged_step) == -1)
    pos = np.asarray(runs.states.pos)
    r = np.asarray(runs.reflex)
    # First state of the perturbed run that differs from its twin's (the hit reaches the body).
    differs = np.any(np.abs(pos[0, 0] - pos[0, 1]) > 0, axis=(1, 2))
    i0 = int(np.argmax(differs))
    assert differs[i0] and i0 >= 3
    for which in (0, 1):  # integer delay, half-step delay
        diff = np.max(np.abs(r[which, 0] - r[which, 1]), axis=(1, 2))
        # Rollout index j holds the reflex of the step from t_{j-1}, which reads the error of
        # state j - 1 - m (integer delay): unchanged by the hit until j = i0 + m + 1.
        np.testing.assert_array_equal(diff[: i0 + m + 1], 0.0)
        assert diff[i0 + m + 1] > 1e-3, (which, diff[i0 + m - 1: i0 + m + 4])
    # The half-step delay reads the interpolated history: half the integer delay's first response.
    first = lambda w: r[w, 0, i0 + m + 1] - r[w, 1, i0 + m + 1]
    np.testing.assert_allclose(first(1), 0.5 * first(0), rtol=0, atol=1e-9 * np.max(np.abs(first(0))))


def test_zero_gain_reflex_reproduces_the_paper(setup, impulse_runs):
    """A [reflex] of zero gain adds exact zeros: the same run as the paper's controller (to the
    round-off of a batched against an unbatched program)."""
    s = setup
    _, runs = impulse_runs
    assert s.gains.reflex is None
    paper = jax.jit(lambda g, p: rollout(s.model, g, p, s.ref, s.options))(s.gains, s.pulses)
    np.testing.assert_allclose(np.asarray(runs.theta[2, 0]), np.asarray(paper.theta), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(runs.states.pos[2, 0]), np.asarray(paper.states.pos), rtol=0, atol=1e-12)
    assert paper.reflex is None


@pytest.fixture(scope="module")
def reflex_fit(setup):
    """A fit of the spinal reflex's gain and delay to joint angles after the push: the problem,
    its compiled evaluation ``log(gain, delay) -> (y, dy/dx)`` and the true values."""
    s = dataclasses.replace(setup, gains=dataclasses.replace(setup.gains, reflex=make_reflex(H, gain=150.0,
                                                                                             delay=0.043)))
    columns = [s.model.dof_names.index(n) for n in s.model.dof_names[:12]]
    problem = F.make_problem(s, "joint_angles", columns, names=("reflex_gain", "reflex_delay"))
    return problem, F.ResponseEvaluator(problem), {"reflex_gain": 180.0, "reflex_delay": 0.047}


def test_gradient_wrt_gain_and_delay_matches_central_differences(reflex_fit):
    """dy/d(log gain, log delay) through the whole rollout against central differences; the
    delay stays inside one grid interval (5.16 h, steps of 0.0006 h)."""
    _, ev, _ = reflex_fit
    x0 = np.log([150.0, 0.043])
    jac = ev(x0).jac
    eps = 1e-4
    fd = np.stack([(ev(x0 + eps * e).y - ev(x0 - eps * e).y) / (2 * eps) for e in np.eye(2)], -1)
    assert np.min(np.linalg.norm(jac, axis=0)) > 1e-4  # both parameters move the joint angles
    np.testing.assert_allclose(jac, fd, rtol=0, atol=2e-5 * np.max(np.abs(fd)))
    np.testing.assert_allclose(np.linalg.norm(jac - fd, axis=0) / np.linalg.norm(fd, axis=0), 0.0, atol=1e-5)


@pytest.mark.extended  # runtime-heavy; experiments/reflex_fit.py runs the full check, test_fitting the driver
def test_synthetic_truth_fit_recovers_gain_and_delay(reflex_fit):
    """Joint angles simulated at known reflex gain and delay plus 0.05 deg of noise: the fit from
    10 % and 3 ms off recovers them within 2 % and 2 ms, and says both are identifiable."""
    problem, ev, truth = reflex_fit
    cal = F.Calibration(setup=None, problem=problem, target=np.zeros(1), weights=np.zeros(1), x0=np.zeros(2))
    target = F.synthetic_target(cal, noise=np.deg2rad(0.05), seed=1, evaluator=ev, values=truth)
    res = F.fit(ev, target, np.ones_like(target), np.log([162.0, 0.044]), progress=False, strict=True)
    assert abs(res.values["reflex_gain"] / truth["reflex_gain"] - 1) < 0.02
    assert abs(res.values["reflex_delay"] - truth["reflex_delay"]) < 0.002
    assert res.identifiable == {"reflex_gain": True, "reflex_delay": True}
    assert 0 < res.standard_errors["reflex_delay"] < 0.002 and res.ks == float(problem.gains.ks)


def test_reflex_table_parses_and_refuses_bad_values():
    cfg = simulation_config({"reflex": {"gain": 50, "delay": 0.03, "one_sided": True}}, "r.toml")
    rx = cfg.reflex.build(H)
    assert float(rx.spinal.delay) == 0.03 and float(rx.one_sided) == 1.0 and float(rx.long_latency.gain) == 0.0
    assert rx.steps == int(np.ceil(0.12 / H - 1e-9)) + 2
    assert simulation_config({}, "r.toml").reflex is None
    for table, field in (({"delay": -0.01}, "reflex.delay"), ({"gian": 3}, "reflex.gian"),
                         ({"delay": 0.2, "max_delay": 0.1}, "reflex.delay"), ({"max_delay": 3.0}, "reflex.max_delay"),
                         ({"one_sided": "yes"}, "reflex.one_sided")):
        with pytest.raises(ConfigError, match=f"r.toml: field '{field}'"):
            simulation_config({"reflex": table}, "r.toml")
