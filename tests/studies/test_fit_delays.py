"""A fitted delay longer than the delay history the fit simulated is not the model's delay: the
rollout reads the oldest entry, so it ran a shorter one and the fit's gradient along it is zero.
Such a fit is reported (``out_of_range``, exit status 3), not returned as converged."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.physics.reflex import delayed, make_reflex
from neuromotor.studies.fit import driver
from neuromotor.studies.gains import delay_limits

H = 1.0 / 120.0


@pytest.mark.parametrize("max_delay", [0.05, 0.3, 0.31])
def test_the_delay_limit_is_where_the_history_stops_delaying(max_delay):
    rx = make_reflex(H, max_delay=max_delay)
    limit = delay_limits(SimpleNamespace(reflex=rx, balance=None), H)["reflex_delay"]
    assert limit >= max_delay
    buf = jax.random.normal(jax.random.PRNGKey(0), (rx.steps, 4, 3), jnp.float64)
    at = np.asarray(delayed(buf, limit, H))
    np.testing.assert_array_equal(np.asarray(delayed(buf, 1.5 * limit, H)), at)  # clamped beyond
    assert np.abs(np.asarray(delayed(buf, limit - 0.5 * H, H)) - at).max() > 1e-3  # still delaying below
    d_rate = jax.grad(lambda d: jnp.sum(delayed(buf, d, H)))
    assert float(d_rate(limit + 0.25 * H)) == 0.0 and float(d_rate(limit - 0.25 * H)) != 0.0


class _Evaluator:
    """What the driver's last check reads of a ResponseEvaluator: the problem, and a finite,
    undiverged response at any x."""

    def __init__(self, problem):
        self.problem = problem

    def __call__(self, x):
        return SimpleNamespace(y=np.zeros(3), diverged=np.array([-1]))


def _finish(delay: float, names=("reflex_delay", "ks")):
    rx = make_reflex(H, max_delay=0.3)
    problem = SimpleNamespace(names=names, gains=SimpleNamespace(reflex=rx, balance=None), options=SimpleNamespace(h=H))
    evaluator = _Evaluator(problem)
    track = SimpleNamespace(history=[], last_good=None)
    opts = SimpleNamespace(max_steps=10)
    x = np.log([delay, 400.0])
    return driver._final_status(evaluator, "optimistix_lm", opts, track, x, 3, True, "")


def test_a_fit_whose_delay_left_the_history_is_not_converged():
    limit = delay_limits(SimpleNamespace(reflex=make_reflex(H, max_delay=0.3), balance=None), H)["reflex_delay"]
    status, _, _, message = _finish(0.99 * limit)
    assert status == "converged"
    status, _, _, message = _finish(1.01 * limit)
    assert status == "out_of_range"
    assert message.startswith("reflex_delay = ") and "[reflex] max_delay and fit again" in message
