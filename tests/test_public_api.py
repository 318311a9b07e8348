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


def test_x64_is_on_unless_the_user_chose_and_float64_is_never_run_in_float32(tmp_path):
    """``import neuromotor`` turns x64 on, but an explicit JAX_ENABLE_X64 stands; a float64 run
    with x64 off is refused (one line, exit 2), never silently run in float32."""
    import os

    code = "import jax, neuromotor; print(jax.config.jax_enable_x64)"
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    run = lambda cmd, **extra: subprocess.run(cmd, capture_output=True, text=True, env={**env, **extra}, cwd=tmp_path)
    assert run([sys.executable, "-c", code]).stdout.strip() == "True"
    assert run([sys.executable, "-c", code], JAX_ENABLE_X64="0").stdout.strip() == "False"
    (tmp_path / "hit.toml").write_text('[[perturbation]]\nbody = "chest"\nmagnitude = 10.0\n')
    out = run([sys.executable, "-m", "neuromotor", "simulate", "hit.toml", "-o", "run.npz"], JAX_ENABLE_X64="0")
    assert out.returncode == 2 and "field 'sim.dtype' is float64 but JAX runs with x64 off" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and not (tmp_path / "run.npz").exists()


def test_step_by_step_equals_the_rollout():
    """Three calls of ``neuromotor.step`` from ``init_data`` reproduce the scanned rollout's states."""
    cfg = neuromotor.SimulationConfig(duration=0.05, perturbations=[dict(neuromotor.DEFAULT_HIT, start=0.0)])
    setup = neuromotor.prepare(cfg)
    sim = neuromotor.SimModel(setup.model, setup.ref, setup.options)
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
