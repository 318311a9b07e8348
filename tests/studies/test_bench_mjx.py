"""MuJoCo MJX in ``neuromotor bench`` (neuromotor.studies.bench_mjx): MJX steps the exported model
as MuJoCo C does, so the bench compares engines on one model; the comparison's figures are finite
and positive; without MJX the bench says so in one line. No timing is asserted."""

import math
import sys
import time

import jax
import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")
pytest.importorskip("mujoco.mjx")

from neuromotor import compiler  # noqa: E402
from neuromotor.studies import bench, bench_mjx  # noqa: E402
from neuromotor.studies.simulate import load_character  # noqa: E402

N_STEPS = 20
FAST = dict(compiler.CPU_COMPILER_OPTIONS)  # cuts MJX's compile time ~2.5x; same results
# float64 MJX and MuJoCo C run the same implicitfast arithmetic in another order: they agree to
# round-off over 20 steps (measured ~1e-15), far inside this.
TOL_F64 = 1e-9

TINY = """<mujoco><option timestep="0.01" integrator="implicitfast"/>
  <worldbody><body><freejoint/><inertial pos="0 0 0" mass="2" diaginertia="0.1 0.2 0.3"/>
    <body pos="0 0 -0.3"><joint name="a" type="hinge" axis="1 0 0"/>
      <inertial pos="0 0 -0.15" mass="1" diaginertia="0.02 0.02 0.01"/>
      <body pos="0 0 -0.3"><joint name="b" type="hinge" axis="0 1 0"/>
        <inertial pos="0 0 -0.1" mass="0.5" diaginertia="0.01 0.01 0.005"/></body></body></body></worldbody>
  <actuator><position joint="a" kp="100" kv="10"/><position joint="b" kp="100" kv="10"/></actuator></mujoco>"""


def test_mjx_steps_the_exported_model_like_mujoco_c():
    """The bench's MJX trajectory (float64, the default character exported at the bench's step) and
    MuJoCo C's mj_step, from a random pose and random velocities, agree over 20 steps."""
    character, _ = load_character(None)
    rng = np.random.default_rng(1)
    mj, d0 = bench.mujoco_start(character, bench.H, rng.uniform(-0.5, 0.5, character.model.n_dofs))
    assert mj.nu == character.model.n_dofs and mj.opt.timestep == bench.H
    d0.qvel[:] = rng.standard_normal(mj.nv)
    mujoco.mj_forward(mj, d0)
    m, d = bench_mjx.put(mj, d0, "float64")
    args = (jax.numpy.ones(2), m, d)
    run, _ = bench_mjx.compile_in(bench_mjx.trajectory(N_STEPS), args, "float64", FAST)
    qpos = np.asarray(run(*args))
    c_qpos = []
    for _ in range(N_STEPS):
        mujoco.mj_step(mj, d0)
        c_qpos.append(d0.qpos.copy())
    assert np.max(np.abs(c_qpos[-1] - c_qpos[0])) > 1e-2  # the state moves
    assert np.max(np.abs(qpos - np.array(c_qpos))) < TOL_F64


def _finite_positive(tree) -> list:
    bad = []
    for path, value in jax.tree_util.tree_leaves_with_path(tree):
        if isinstance(value, float) and not (math.isfinite(value) and value > 0):
            bad.append((jax.tree_util.keystr(path), value))
    return bad


def test_compare_gives_finite_positive_figures_on_a_tiny_model(monkeypatch):
    """float32 only, to keep the compile cost low: the float64 programs are the same code, and the
    float64 trajectory is checked against MuJoCo C above. Our batch programs advance a virtual
    clock by 1000 s a call, so the batch-over-one figure is the arithmetic's, not the host's."""
    offset, real = [0.0], time.perf_counter
    monkeypatch.setattr(bench_mjx.time, "perf_counter", lambda: real() + offset[0])

    def virtual_call(seconds=1000.0):
        offset[0] += seconds  # the same time per call: 0.5 of it per trajectory in a batch of 2

    mj = mujoco.MjModel.from_xml_string(TINY)
    d0 = mujoco.MjData(mj)
    d0.qpos[7:] = [0.3, -0.2]  # the servos pull towards ctrl = 0
    mujoco.mj_forward(mj, d0)
    work = np.arange(1000.0)
    ours = {name: (lambda: np.sum(work ** 2)) for name in ("rollout", "batch", "jacfwd", "jacfwd_rollout")}
    ours["batch"] = ours["batch_one"] = virtual_call
    ours["batch_one_device"] = lambda: virtual_call(1250.0)  # the batch unsplit: 1.25x the time
    r = bench_mjx.compare(mj, d0, ours, steps=3, batch=2, batch_steps=2, rounds=2, dtypes=("float32",),
                          compiler_options=FAST)
    f32 = dict(r["float32"])
    diff = f32.pop("max_qpos_diff_vs_c")
    assert not _finite_positive({"c": r["c"], "ours": r["ours"], "float32": f32})
    assert set(f32["ours_over_mjx"]) == {"step_time", "batch_throughput", "batch_throughput_one_device", "jacfwd_time"}
    assert set(f32["compile_s"]) == {"rollout", "batch", "jacfwd"}
    assert diff < 1e-4  # the same model as MuJoCo C, to float32's precision
    lines = []
    bench_mjx.log_figures(r, lines.append, {"rollout": 1.0, "batch": 1.0, "jacfwd": 1.0})
    assert abs(r["ours"]["batch_over_one"] - 0.5) < 1e-3  # a batch of 2 in the time of one
    split = r["ours"]["batch_steps_per_s"] / r["ours"]["batch_one_device_steps_per_s"]
    ratios = f32["ours_over_mjx"]
    assert abs(split - 1.25) < 1e-3 and abs(ratios["batch_throughput"] / ratios["batch_throughput_one_device"] - 1.25) < 1e-3
    assert len(lines) == 8 and not any("nan" in line for line in lines)


def test_bench_says_in_one_line_why_mjx_is_skipped(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco.mjx", None)  # import of mujoco.mjx fails
    monkeypatch.delattr(mujoco, "mjx", raising=False)
    why = bench_mjx.unavailable()
    assert why is not None and "\n" not in why and "neuromotor[mjx]" in why
    lines = []
    assert bench.mjx_beside(None, None, {}, {}, 1, lines.append) == {"skipped": why}
    assert lines == [f"MJX: skipped ({why})"]
