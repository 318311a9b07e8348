"""Angle wrap: every metric uses the shortest angle difference, and stored angles are continuous.

Synthetic theta arrays that cross +-pi: a joint whose angle is reported on the other branch
(356 degrees away) has moved by -4 degrees, not 356 (issue 16, item 1).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.rotations import continuous_angles
from neuromotor.studies import metrics as mx
from neuromotor.studies.fit import acceleration_deg, deviation_deg


def _crossing(T=200, n=3, offset=0.05):
    """An unperturbed motion that sweeps through +pi, and a perturbed one ``offset`` rad away
    that is stored wrapped to (-pi, pi] (so it jumps by 2 pi where it crosses +pi)."""
    t = np.linspace(0.0, 1.0, T)
    base = np.stack([2.9 + 0.5 * t, -2.9 - 0.5 * t, 0.3 * np.sin(6 * t)][:n], axis=1)
    pert = base + offset
    pert_wrapped = np.arctan2(np.sin(pert), np.cos(pert))
    return t, base, pert, pert_wrapped


def test_wrap_angle_is_shortest_and_smooth():
    a = jnp.array([0.1, np.pi - 0.01, np.pi + 0.01, -np.pi - 0.01, 2 * np.pi + 0.2, -6.2])
    w = np.asarray(mx.wrap_angle(a))
    assert np.all(np.abs(w) <= np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(np.asarray(a)), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(np.asarray(a)), atol=1e-12)
    np.testing.assert_allclose(w[[0, 4]], [0.1, 0.2], atol=1e-12)
    np.testing.assert_allclose(mx.wrap_angle_np(np.asarray(a)), w, atol=1e-12)
    g = jax.vmap(jax.grad(mx.wrap_angle))(a)
    np.testing.assert_allclose(np.asarray(g), 1.0, atol=1e-12)


def test_deviation_uses_wrapped_difference():
    _, base, _, pert_wrapped = _crossing()
    # The stored perturbed angles jump by 2 pi: the raw difference reaches ~2 pi there.
    assert np.abs(pert_wrapped - base).max() > 6.0
    dev = np.asarray(mx.deviation(jnp.asarray(pert_wrapped), jnp.asarray(base)))
    np.testing.assert_allclose(dev, np.rad2deg(0.05), rtol=1e-9)
    dev_sub = np.asarray(mx.deviation(jnp.asarray(pert_wrapped), jnp.asarray(base), dofs=[0]))
    np.testing.assert_allclose(dev_sub, np.rad2deg(0.05), rtol=1e-9)
    assert mx.rms_error_deg(pert_wrapped, base) == pytest.approx(np.rad2deg(0.05), rel=1e-9)
    # The recovery metrics read the wrapped signal: peak 2.86 deg, not ~360.
    m = mx.recovery_metrics(np.linspace(0, 1, len(dev)), dev, 0.0)
    assert m["peak_deviation_deg"] == pytest.approx(np.rad2deg(0.05), rel=1e-9)


def test_a_356_degree_jump_is_a_4_degree_move():
    T = 50
    base = np.zeros((T, 2))
    pert = base.copy()
    pert[25:, 0] = np.deg2rad(356.0)  # one DOF jumps by 356 deg in one step
    dev = np.asarray(mx.deviation(jnp.asarray(pert), jnp.asarray(base)))
    assert dev.max() == pytest.approx(np.sqrt(4.0 ** 2 / 2), rel=1e-9)
    assert mx.rms_error_deg(pert, base) == pytest.approx(np.sqrt(4.0 ** 2 / 4), rel=1e-9)


def test_fitting_deviation_wrapped_and_differentiable():
    _, base, _, pert_wrapped = _crossing()
    dev = np.asarray(deviation_deg(jnp.asarray(pert_wrapped), jnp.asarray(base)))
    np.testing.assert_allclose(dev, np.rad2deg(0.05), rtol=1e-9)

    # Gradient through the wrap equals the gradient of the unwrapped difference (no 0/0 NaN
    # where the runs coincide, and the 2 pi jump does not change the derivative).
    def f(th):
        return jnp.sum(deviation_deg(th, jnp.asarray(base)) ** 2)

    _, _, pert, _ = _crossing()
    g_wrapped = np.asarray(jax.grad(f)(jnp.asarray(pert_wrapped)))
    g_plain = np.asarray(jax.grad(f)(jnp.asarray(pert)))
    assert np.all(np.isfinite(g_wrapped))
    np.testing.assert_allclose(g_wrapped, g_plain, rtol=1e-7, atol=1e-9)
    jac = jax.jacfwd(lambda th: mx.deviation(th, jnp.asarray(base)))(jnp.asarray(pert_wrapped))
    assert np.all(np.isfinite(np.asarray(jac)))
    g0 = jax.grad(f)(jnp.asarray(base))  # zero deviation: derivative 0, not NaN
    np.testing.assert_allclose(np.asarray(g0), 0.0)


def test_acceleration_is_not_wrapped():
    # Rates are not angles: an acceleration of 10 rad/s^2 stays 10 rad/s^2 (573 deg/s^2).
    T, h = 20, 0.01
    w = np.zeros((T, 1))
    w[:, 0] = 10.0 * np.arange(T) * h  # constant acceleration 10 rad/s^2
    acc = np.asarray(acceleration_deg(jnp.asarray(w), jnp.zeros_like(jnp.asarray(w)), h))
    np.testing.assert_allclose(acc[1:-1], np.rad2deg(10.0), rtol=1e-9)


def test_continuous_angles():
    _, base, pert, pert_wrapped = _crossing()
    out = continuous_angles(pert_wrapped, base)
    np.testing.assert_allclose(out, pert, atol=1e-12)
    assert np.abs(np.diff(out, axis=0)).max() < 0.1
    # A series stored a whole turn away from its reference is put back on the reference's branch.
    shifted = continuous_angles(pert + 2 * np.pi, base)
    np.testing.assert_allclose(shifted, pert, atol=1e-12)
    # Already continuous and on the branch: returned exactly.
    assert np.array_equal(continuous_angles(pert, base), pert)


# --- Fit convergence in the loss (issue 16, item 6) --------------------------------------------

from neuromotor.studies.fit import driver as fitting


def test_loss_is_flat_rule():
    assert fitting.loss_is_flat([5.0, 2.0, 1.0, 1.0 + 1e-10, 1.0 + 2e-10, 1.0 + 2.5e-10])
    assert not fitting.loss_is_flat([5.0, 2.0, 1.0, 1.0 + 1e-10, 1.0 + 2e-10, 1.0 + 1e-6])
    assert not fitting.loss_is_flat([1.0, 1.0, 1.0])  # fewer than 3 changes
    assert not fitting.loss_is_flat([1.0, 1.0, 1.0, 0.999])  # last change 1e-3
    assert not fitting.loss_is_flat([1.0, 0.99, 0.99, 0.99, float("nan")])
    assert fitting.loss_is_flat([0.0, 0.0, 0.0, 0.0])


class _LinearEvaluator:
    """What :func:`fitting.fit` needs of a ResponseEvaluator, for y = A x (no rollouts)."""

    jacobian = "forward"

    def __init__(self):
        import collections

        self.A = np.array([[1.0, 0.5], [0.2, 1.0], [0.3, 0.3]])
        self.problem = type("P", (), {"names": ("ks", "kd"), "n_params": 2, "gains": None})()
        self._cache = collections.OrderedDict()
        self.n_evals, self.diverged_evals = 0, []

    def __call__(self, x):
        x = np.asarray(x, np.float64).reshape(2)
        ev = fitting.Evaluation(x.copy(), self.A @ x, self.A.copy(), np.zeros((1, 1, 1)), np.array([-1]))
        self._cache[x.tobytes()] = ev
        self.n_evals += 1
        return ev


def _fake_solver(path):
    """A run_solver stand-in that walks ``path`` and stops at the step limit, unconverged."""
    def run_solver(name, residual, x0, m, opts, on_iter):
        for k, x in enumerate(path[: opts.max_steps], start=1):
            _EVAL(x)
            on_iter(k, np.asarray(x))
        return np.asarray(path[opts.max_steps - 1]), opts.max_steps, False, "maximum number of steps reached"
    return run_solver


_EVAL = None


@pytest.mark.parametrize("flat", [True, False])
def test_fit_converged_in_loss_is_a_success(monkeypatch, flat):
    global _EVAL
    ev = _LinearEvaluator()
    _EVAL = ev
    x_true = np.array([0.3, -0.2])
    target = ev.A @ x_true + np.array([0.1, -0.1, 0.2])  # no exact fit: the best loss is > 0
    n = 8
    if flat:  # approaches x_true, the last iterates move by round-off-sized amounts only
        path = [x_true + 0.5 ** k * np.array([1.0, 1.0]) if k < 4 else x_true + 1e-9 * (k % 2) for k in range(n)]
    else:  # still descending at the step limit
        path = [x_true + 0.7 ** k * np.array([1.0, 1.0]) for k in range(n)]
    monkeypatch.setattr(fitting, "run_solver", _fake_solver(path))
    opts = fitting.SolverOptions(max_steps=n)
    res = fitting.fit(ev, target, np.ones(3), np.array([1.0, 1.0]), options=opts, progress=False,
                      residual=lambda x: ev.A @ x - target)
    if flat:
        assert res.status == "converged (loss flat)" and res.converged
        assert "loss flat" in res.message
    else:
        assert res.status == "max_steps" and not res.converged
        assert "did not converge" in res.message
