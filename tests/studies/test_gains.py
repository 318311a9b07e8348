"""Issue 36: one way in for gains, ``studies.gains.gains_for`` (no simulation: quick)."""

import jax
import jax.numpy as jnp
import pytest

from neuromotor.config.specs import FIT_PARAMETERS, GainSetting
from neuromotor.physics.control import Gains, pd_tracking_gains
from neuromotor.physics.reflex import make_reflex
from neuromotor.studies.gains import PARAMETERS, UNITS, gain_value, gains_for


def _template(reflex=None) -> Gains:
    n = jnp.arange(1.0, 4.0)
    return Gains(jnp.asarray(1.0), jnp.asarray(2.0), n, 0.1 * n, 10 * n, reflex=reflex)


def test_units_are_a_mapping_by_name():
    assert set(UNITS) == set(PARAMETERS) == set(FIT_PARAMETERS)
    assert UNITS["ks"] == "1/s^2" and UNITS["kd"] == "1/s" and UNITS["reflex_delay"] == "s"


def test_a_setting_sets_the_controller_and_the_pair():
    t = _template()
    paper = gains_for(t, GainSetting(400.0, 20.0))
    assert float(paper.ks) == 400.0 and float(paper.kd) == 20.0 and float(paper.feedforward) == 1.0
    pd = gains_for(t, GainSetting(1e4, 200.0, "pd"))
    want = pd_tracking_gains(t)
    assert float(pd.ks) == 1e4 and float(pd.feedforward) == 0.0
    assert jnp.array_equal(pd.floor, want.floor)


def test_named_values_reach_the_reflex_and_are_traceable():
    t = _template(make_reflex(1 / 120))
    g = gains_for(t, reflex_gain=3.0, long_latency_delay=0.06, kd=5.0)
    assert float(gain_value(g, "reflex_gain")) == 3.0 and float(g.reflex.long_latency.delay) == 0.06
    assert float(gain_value(g, "kd")) == 5.0 and float(g.ks) == 1.0
    d = jax.grad(lambda x: gains_for(t, ks=x[0], reflex_gain=x[1]).per_dof()[0].sum()
                 + gains_for(t, reflex_gain=x[1]).reflex.spinal.gain)(jnp.array([2.0, 1.0]))
    assert float(d[0]) == float(t.scale.sum()) and float(d[1]) == 1.0


def test_a_setting_then_a_reflex_then_named_values():
    t = _template()
    rx = make_reflex(1 / 120, gain=7.0)
    g = gains_for(t, GainSetting(400.0, 20.0), reflex=rx, ks=300.0)
    assert float(g.ks) == 300.0 and float(g.kd) == 20.0 and float(g.reflex.spinal.gain) == 7.0


def test_unknown_or_reflexless_names_are_refused():
    with pytest.raises(ValueError, match="unknown gain parameter"):
        gains_for(_template(), kp=1.0)
    with pytest.raises(ValueError, match="needs a controller with a reflex"):
        gains_for(_template(), reflex_gain=1.0)
