"""Issue 6: the CPU compiler options change how the rollout is compiled, not what it computes."""

import pathlib

import jax
import jax.numpy as jnp
import pytest

from conftest import CLIPS
from neuromotor import compiler
from neuromotor.config import DEFAULT_HIT, SimulationConfig
from neuromotor.physics.dynamics import simulate
from neuromotor.studies.simulate import load_character, prepare, simulate_jit


@pytest.fixture(scope="module")
def short_hit():
    character, traj = load_character(CLIPS["mocapbank"])
    hit = dict(DEFAULT_HIT, magnitude=400.0, start=0.05)
    return prepare(SimulationConfig(duration=0.2, perturbations=[hit]), character, traj)


def test_options_are_cpu_debug_options_and_can_be_switched_off(monkeypatch):
    opts = compiler.compiler_options()
    assert opts == compiler.CPU_COMPILER_OPTIONS and all(k.startswith("xla_cpu_") for k in opts)
    monkeypatch.setenv("NEUROMOTOR_XLA_TUNING", "0")
    assert compiler.compiler_options() == {}


def test_tuned_rollout_equals_default_build(short_hit):
    s = short_hit
    args = (s.sim_model, s.params)
    # The module-level program (what `neuromotor simulate` runs) against XLA's default build.
    tuned = simulate_jit.lower(*args).compile()
    # XLA's defaults restored explicitly: the suite's XLA_FLAGS (conftest) turn the emitters off.
    default = jax.jit(simulate).lower(*args).compile(compiler_options={"xla_cpu_use_fusion_emitters": True})
    # The options took effect: no small dot is handed to the YNNPACK library.
    assert "__ynn_fusion" not in tuned.as_text()
    a, b = tuned(*args), default(*args)
    assert int(a.diverged_step) == int(b.diverged_step) == -1
    # The joints move (mocap and hit) by more than a milliradian; the two builds agree to round-off.
    assert float(jnp.max(jnp.abs(a.theta - a.theta[0]))) > 1e-3
    assert float(jnp.max(jnp.abs(a.theta - b.theta))) < 1e-11
    assert float(jnp.max(jnp.abs(a.states.pos - b.states.pos))) < 1e-11


def test_a_package_program_runs_inside_another_program():
    """JAX takes compiler options only on top-level programs: a package program (built by
    compiler.jit) called from inside a user's jit or grad is traced into it, with the same value."""
    f = compiler.jit(lambda x, n: jnp.sin(x) ** n, static_argnames="n")
    x = jnp.linspace(0.0, 1.0, 5)
    top = f(x, n=3)
    inner = jax.jit(lambda x: f(x, n=3))(x)
    grad = jax.grad(lambda x: jnp.sum(f(x, n=3)))(x)
    assert float(jnp.max(jnp.abs(top - jnp.sin(x) ** 3))) < 1e-15
    assert float(jnp.max(jnp.abs(inner - top))) < 1e-15
    assert float(jnp.max(jnp.abs(grad - 3 * jnp.sin(x) ** 2 * jnp.cos(x)))) < 1e-14


CORES_SCRIPT = """
import json, os, sys, jax
from neuromotor import compiler
from neuromotor.errors import UserError
try:
    got = compiler.use_cpu_cores(split=sys.argv[1] == "split")
except UserError as e:
    got = "error: " + str(e)
print("RESULT" + json.dumps([got, len(jax.devices()), os.environ.get("PJRT_NPROC")]))
"""


def _cores(env: dict, script: str = CORES_SCRIPT, split: bool = True, threads: bool = False):
    import json
    import os
    import subprocess
    import sys

    base = {k: v for k, v in os.environ.items()
            if k not in ("NEUROMOTOR_CPU_DEVICES", "JAX_NUM_CPU_DEVICES", "PJRT_NPROC", "NPROC")}
    base["XLA_FLAGS"] = " ".join(f for f in base.get("XLA_FLAGS", "").split()
                                 if "device_count" not in f and "intra_op" not in f)
    proc = subprocess.run([sys.executable, "-c", script, "split" if split else "single"],
                          env={**base, "JAX_PLATFORMS": "cpu", **env}, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = json.loads([ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")][-1][6:])
    return got if threads else got[:2]


def test_use_cpu_cores_gives_one_device_per_core_unless_the_count_was_chosen():
    import os

    assert _cores({"NEUROMOTOR_CPU_DEVICES": "3"}) == [3, 3]
    assert _cores({"NEUROMOTOR_CPU_DEVICES": "off"}) == [None, 1]
    assert _cores({"NEUROMOTOR_CPU_DEVICES": "1"}) == [None, 1]
    auto = compiler.cpu_cores()
    assert _cores({}) == ([auto, auto] if auto > 1 else [None, 1])
    # Chosen already: the host device count or one thread per process (distributed sweeps), or jax's own.
    flags = os.environ.get("XLA_FLAGS", "")
    assert _cores({"NEUROMOTOR_CPU_DEVICES": "3", "XLA_FLAGS": flags + " --xla_force_host_platform_device_count=2"}) \
        == [None, 2]
    assert _cores({"NEUROMOTOR_CPU_DEVICES": "3", "XLA_FLAGS": flags + " intra_op_parallelism_threads=1"})[0] is None
    assert _cores({"NEUROMOTOR_CPU_DEVICES": "3", "JAX_NUM_CPU_DEVICES": "2"}) == [None, 2]
    # Too late once JAX's backends run: the count is fixed at start-up.
    late = CORES_SCRIPT.replace("try:", "jax.devices()\ntry:")
    assert _cores({"NEUROMOTOR_CPU_DEVICES": "3"}, late) == [None, 1]
    got = _cores({"NEUROMOTOR_CPU_DEVICES": "many"})[0]
    assert got.startswith("error: NEUROMOTOR_CPU_DEVICES:") and "'many'" in got
    # Single runs (split=False): one device unless a count is given; XLA's threads left alone.
    assert _cores({}, split=False, threads=True) == [None, 1, None]
    assert _cores({"NEUROMOTOR_CPU_DEVICES": "3"}, split=False, threads=True) == [3, 3, None]


THREAD_SCRIPT = """
import json, os
from neuromotor import compiler
got = compiler.one_runtime_thread()
print("RESULT" + json.dumps([got, os.environ.get("PJRT_NPROC")]))
"""


def test_one_runtime_thread_unless_the_user_chose_or_jax_runs():
    assert _cores({}, THREAD_SCRIPT) == [True, "1"]
    assert _cores({"PJRT_NPROC": "4"}, THREAD_SCRIPT) == [False, "4"]
    assert _cores({"NPROC": "4"}, THREAD_SCRIPT) == [False, None]
    late = THREAD_SCRIPT.replace("got =", "import jax; jax.devices()\ngot =")
    assert _cores({}, late) == [False, None]


def test_the_cli_asks_for_one_runtime_thread_only_for_a_free_root_run(tmp_path):
    """Only a free-root trajectory, whose contact step it speeds up, gets one thread; the pool
    stays for the rest (docs/benchmarks.md, "Thread hand-offs")."""
    from neuromotor.cli import _free_root_run, build_parser

    configs = pathlib.Path(__file__).resolve().parents[1] / "configs"

    def free(*argv):
        return _free_root_run(build_parser().parse_args(list(argv)))

    out = str(tmp_path / "run.npz")
    assert free("simulate", str(configs / "stand_balance.toml"), "-o", out)
    assert free("simulate", str(configs / "walk_free.toml"), "-o", out)
    assert not free("simulate", "-o", out)
    assert not free("simulate", str(configs / "simulate_default.toml"), "-o", out)
    assert not free("simulate", str(configs / "ball_hit.toml"), "-o", out)
    assert free("bench", "--free-only")
    assert not free("bench")
    assert free("fit", str(configs / "fit_balance.toml"), "-o", str(tmp_path / "fit"))
    assert not free("fit", str(configs / "fit_synthetic.toml"), "-o", str(tmp_path / "fit"))
    assert not free("fit", str(tmp_path / "missing.toml"), "-o", str(tmp_path / "fit"))  # the command reports it
    assert not free("sweep", str(configs / "sweep_magnitude.toml"))


HANDOFF_SCRIPT = """
import glob, sys
from neuromotor import compiler
if sys.argv[1] == "single":
    compiler.one_runtime_thread()
    compiler.use_cpu_cores(split=False)
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
from neuromotor.physics.contact.lcp import solve_lcp_pgs

def switches():
    n = 0
    for f in glob.glob("/proc/self/task/*/status"):
        n += sum(int(ln.split()[1]) for ln in open(f) if ln.startswith("voluntary_ctxt_switches"))
    return n

w = jax.random.normal(jax.random.PRNGKey(1), (48, 48))
w = w @ w.T / 48 + jnp.eye(48)
step = lambda x: x + 1e-3 * solve_lcp_pgs(w, x - 1.0, 0.8, jnp.ones(16, bool), jnp.zeros((16, 3)), 8, 40).reshape(-1)
f = compiler.jit(lambda x: jax.lax.scan(lambda c, _: (step(c), None), x, None, length=200)[0])
x = jnp.zeros(48)
jax.block_until_ready(f(x))
before = switches()
jax.block_until_ready(f(x))
print("RESULT", (switches() - before) / 200)
"""


@pytest.mark.skipif(not pathlib.Path("/proc/self/task").exists(), reason="counts thread switches in /proc")
def test_a_single_run_hands_no_kernels_to_other_threads():
    """XLA:CPU's pool took part of the PGS step's kernels about once a step on a 2-core host (the
    main thread then sleeps until they are done): with one runtime thread and one device, none."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("NEUROMOTOR_CPU_DEVICES", "PJRT_NPROC", "NPROC")}
    proc = subprocess.run([sys.executable, "-c", HANDOFF_SCRIPT, "single"], env={**env, "JAX_PLATFORMS": "cpu"},
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    per_step = float([ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")][-1].split()[1])
    assert per_step < 0.2, per_step
