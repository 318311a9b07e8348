"""The curated API of ``neuromotor``: every name resolves, the package imports light, and the
named-stage step is the rollout's step."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

import neuromotor


def test_every_public_name_resolves():
    for name in neuromotor.__all__:
        assert getattr(neuromotor, name) is not None, name
    assert set(neuromotor.__all__) <= set(dir(neuromotor))


def test_import_is_light():
    """``import neuromotor`` (what every CLI call pays) loads neither the physics nor pyvista."""
    code = ("import sys, neuromotor; heavy = [m for m in ('pyvista', 'matplotlib', 'neuromotor.physics.dynamics')"
            " if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_step_by_step_equals_the_rollout():
    """Three calls of ``neuromotor.step`` from ``init_data`` reproduce the scanned rollout's states."""
    cfg = neuromotor.SimulationConfig(duration=0.05, perturbations=[dict(neuromotor.DEFAULT_HIT, start=0.0)])
    setup = neuromotor.prepare(cfg)
    sim = neuromotor.SimModel(setup.model, setup.ref, setup.sim)
    params = neuromotor.Params(setup.gains, setup.pulses)
    run = neuromotor.simulate(sim, params)
    data = neuromotor.init_data(sim, params)
    one = jax.jit(neuromotor.step)
    for k in range(3):
        data = one(sim, params, data)
        assert int(data.k) == k + 1
        np.testing.assert_allclose(data.state.pos, run.states.pos[k + 1], rtol=0, atol=1e-13)
        np.testing.assert_allclose(data.state.quat, run.states.quat[k + 1], rtol=0, atol=1e-13)
        assert float(data.info.residual) < 1e-10
        assert float(data.info.violation) < 1e-10
    # The hit at t = 0 is in the step: without it the third state differs.
    quiet = neuromotor.Params(setup.gains, jax.tree_util.tree_map(jnp.zeros_like, setup.pulses))
    free = neuromotor.simulate(sim, quiet)
    assert float(jnp.max(jnp.abs(free.states.vel[3] - data.state.vel))) > 1e-4
