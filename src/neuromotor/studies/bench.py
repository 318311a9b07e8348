"""Speed benchmark: ``neuromotor bench``.

Prints, after compilation, for the 19-joint default clip at h = 1/120 s:

* one trajectory: steps per second, real-time factor, compile time, and the split of a step
  between the Jacobians K, D (Eq. 2), the KKT solve, post-stabilization and the rest;
* a ``vmap`` batch at sizes 1, 8, 64, 256 (short rollouts): total simulated steps per second,
  split over the CPU devices as sweeps run it (one per core from the command line,
  :func:`neuromotor.compiler.use_cpu_cores`) and, in alternation, on one device; and at the
  largest size, the same split of a step per trajectory (:func:`batch_split`);
* ``jax.jacfwd`` over (ks, kd) through a 1 s rollout, relative to the rollout itself;
* inverse dynamics of whole clips (Eq. 3) after compile and its compile time;
* MuJoCo (optional) on the exported MJCF (:func:`neuromotor.io.mjcf.model_to_mjcf`): one thread,
  implicitfast, PD servos on every hinge, same skeleton, masses and time step; and the ratio;
* the free root on the ground (issue 38, docs/balance.md): the clip's most upright frame standing
  with the postural loop, beside the same pose on the driven root (the paper), interleaved;
* MuJoCo MJX (optional, float64 and float32) on that same model beside MuJoCo C and ours, timed in
  interleaved rounds (:mod:`neuromotor.studies.bench_mjx`).

Every time is the best of several repeats (the figures are meant for a shared machine).
Component times are measured on their own inside a ``lax.scan`` over the states of a rollout,
so dispatch overhead does not count; "rest" is the full step minus the measured parts.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

from neuromotor import compiler
from neuromotor.config import DEFAULT_HIT, SimulationConfig, simulation_config
from neuromotor.physics import dynamics as dy, solvers
from neuromotor.physics.constraints import constraint_count, post_stabilize
from neuromotor.physics.inverse import inverse_dynamics
from neuromotor.physics.perturbation import build_pulses
from neuromotor.physics.stiffness import DenseStiffness, StiffBlocks
from neuromotor.physics.system import world_inertia
from neuromotor.studies.simulate import config_character, prepare

H = 1.0 / 120.0


def _best(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t)
    return best


def _compile(fn, *args):
    """(compiled, wall seconds to trace and compile)."""
    t = time.perf_counter()
    compiled = compiler.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - t


def cpu_name() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine() -> str:
    dev = jax.devices()[0]
    import os

    return f"{os.cpu_count()}-core CPU ({cpu_name()}), JAX {jax.__version__} on {dev.platform}, float64" + (
        "" if dev.platform == "cpu" else f" ({dev.device_kind})"
    )


def _clip_config(clip, top: dict | None) -> SimulationConfig:
    """``clip`` (None: the embedded one) as a config with the top-level keys ``top`` (units,
    up_axis, stature, body_mass, ...) reads it."""
    return simulation_config({**(top or {}), **({} if clip is None else {"clip": str(clip)})}, "<bench>")


def _setup(clip, seconds: float, solver: str, top: dict | None = None):
    """The default hit on ``clip``; ``top``: the clip's top-level config keys."""
    config = dataclasses.replace(
        _clip_config(clip, top),
        duration=seconds,
        perturbations=[dataclasses.replace(DEFAULT_HIT, start=min(0.3, seconds / 2))],
    )
    setup = prepare(config)
    return dataclasses.replace(setup, options=dataclasses.replace(setup.options, solver=solvers.Solver(solver)))


def _stages(setup) -> dict:
    """The parts of a step as functions ``body(k, state, ref)``: the Jacobians K, D (Eq. 2),
    the KKT solve and post-stabilization, for the solver of ``setup.options``."""
    m, g, cfg = setup.model, setup.gains, setup.options
    solver = solvers.get(cfg.solver)
    n = m.n_bodies
    sim = lambda ref: dy.SimModel(m, ref, cfg)

    def jac(k, st, ref):
        return dy.stiff_forces(
            sim(ref), g, dy.reference_inputs(sim(ref), g, k), st, solver.tree_blocks, solver.unrolled
        )

    # Stand-ins for the K, D terms (the solve's cost does not depend on their values).
    if solver.tree_blocks:
        k_off, d_off = jnp.full((n - 1, 3, 3), 1e-3), jnp.zeros((n - 1, 3, 3))
        stiff: StiffBlocks | DenseStiffness = StiffBlocks(
            jnp.zeros((n, 3)),
            jnp.broadcast_to(0.01 * jnp.eye(3), (n, 3, 3)),
            k_off,
            k_off,
            jnp.zeros((n, 3, 3)),
            d_off,
            d_off,
        )
    else:
        stiff = DenseStiffness(jnp.zeros(6 * n), jnp.full((6 * n, 6 * n), 1e-3), jnp.zeros((6 * n, 6 * n)))
    nc = constraint_count(m, cfg.driven, cfg.free_root)

    def solve(k, st, ref):
        rot = st.rot
        system = solver.assemble(m, cfg, rot, world_inertia(m, rot), stiff, cfg.h)
        return solver.solve(system, st.v.reshape(n, 6), jnp.ones(nc))[0]

    def post(k, st, ref):
        return post_stabilize(m, cfg, solver, st.pos, st.quat, ref.pose_targets(k + 1))

    return {"jacobians": jac, "kkt_solve": solve, "post_stabilization": post}


def _reduce(out):
    return sum(jnp.sum(x) for x in jax.tree_util.tree_leaves(out))


def single(setup, repeats: int) -> tuple[dict, object]:
    """One trajectory: speed, compile time and the split of a step; and the compiled rollout
    (a zero-argument callable, for the interleaved comparison with MuJoCo)."""
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options
    run_fn = lambda m, g, p, ref: dy.simulate(dy.SimModel(m, ref, cfg), dy.Params(g, p))
    comp, compile_s = _compile(run_fn, m, g, p, ref)
    run = comp(m, g, p, ref)
    total = _best(lambda: comp(m, g, p, ref), repeats)
    per_step = total / cfg.n_steps
    states = jax.tree_util.tree_map(lambda x: x[:-1], run.states)
    ks = jnp.arange(cfg.n_steps)

    def scan_of(body):
        def f(states, ref):
            step = lambda acc, xs: (acc + _reduce(body(xs[0], xs[1], ref)), None)
            return jax.lax.scan(step, jnp.zeros(()), (ks, states))[0]

        c, _ = _compile(f, states, ref)
        return _best(lambda: c(states, ref), repeats) / cfg.n_steps

    split = {name: scan_of(body) for name, body in _stages(setup).items()}
    split["rest"] = max(per_step - sum(split.values()), 0.0)
    return {
        "solver": cfg.solver,
        "steps": cfg.n_steps,
        "compile_s": compile_s,
        "step_us": per_step * 1e6,
        "steps_per_s": 1.0 / per_step,
        "real_time_factor": cfg.h / per_step,
        "split_us": {name: t * 1e6 for name, t in split.items()},
    }, lambda: comp(m, g, p, ref)


def batch_split(setup, size: int, repeats: int) -> dict:
    """The parts of a step (as in :func:`single`) and the whole step under ``vmap`` over
    ``size`` states of a rollout: wall microseconds per trajectory-step. In a batch the
    kernel count no longer dominates; this shows where the arithmetic and copies go."""
    batched = dataclasses.replace(setup.options, solver=solvers.Solver(setup.options.solver).batched())
    setup = dataclasses.replace(setup, options=batched)
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options
    run = compiler.jit(lambda m, g, p, ref: dy.simulate(dy.SimModel(m, ref, cfg), dy.Params(g, p)))(m, g, p, ref)
    idx = np.arange(size) % cfg.n_steps
    states = jax.tree_util.tree_map(lambda x: x[idx], run.states)
    ks = jnp.asarray(idx)
    params = dy.Params(g, p)

    def whole(k, st, ref):
        sim = dy.SimModel(m, ref, cfg)
        out = dy.step(sim, params, dy.data_at(sim, params, k, st))
        return out.state, out.info

    bodies = dict(_stages(setup), step=whole)
    out: dict[str, float] = {"batch": size}
    for name, body in bodies.items():
        c, _ = _compile(
            lambda ks, states, ref: _reduce(jax.vmap(body, in_axes=(0, 0, None))(ks, states, ref)), ks, states, ref
        )
        out[name] = _best(lambda: c(ks, states, ref), repeats) / size * 1e6
    return out


def interleaved(runs: dict, repeats: int) -> dict[str, float]:
    """Best wall time of each zero-argument callable over ``max(repeats, 5)`` rounds, one call of
    each per round (the host's speed drifts too much between processes, or even minutes apart,
    for separate runs to be compared). Pass compiled programs, or warm them up first."""
    best = {name: np.inf for name in runs}
    for _ in range(max(repeats, 5)):
        for name, fn in runs.items():
            best[name] = min(best[name], _best(fn, 1))
    return best


def compiler_options_ab(setup, repeats: int) -> dict:
    """The rollout compiled with :data:`compiler.CPU_COMPILER_OPTIONS` and with XLA's defaults."""
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options
    fn = lambda m, g, p, ref: dy.simulate(dy.SimModel(m, ref, cfg), dy.Params(g, p))
    progs = {
        "tuned": jax.jit(fn).lower(m, g, p, ref).compile(compiler_options=dict(compiler.CPU_COMPILER_OPTIONS)),
        "default": jax.jit(fn).lower(m, g, p, ref).compile(),
    }
    diff = float(jnp.max(jnp.abs(progs["tuned"](m, g, p, ref).theta - progs["default"](m, g, p, ref).theta)))
    best = interleaved({k: (lambda c=c: c(m, g, p, ref)) for k, c in progs.items()}, repeats)
    return {
        "tuned_us": best["tuned"] / cfg.n_steps * 1e6,
        "default_us": best["default"] / cfg.n_steps * 1e6,
        "speedup": best["default"] / best["tuned"],
        "max_theta_diff_rad": diff,
    }


def stabilization_ab(setup, repeats: int, steps=(1, 2)) -> list[dict]:
    """The rollout with each number of post-stabilization Newton steps: time per step (timed
    in alternation), the largest constraint violation left, and the largest difference in
    joint angles from the last entry of ``steps``."""
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options
    progs = {}
    for n in steps:
        c = dataclasses.replace(cfg, stabilization_steps=n)
        run_n = lambda m, g, p, ref, c=c: dy.simulate(dy.SimModel(m, ref, c), dy.Params(g, p))
        progs[n] = compiler.jit(run_n).lower(m, g, p, ref).compile()
    runs = {n: progs[n](m, g, p, ref) for n in steps}
    best = interleaved({k: (lambda c=c: c(m, g, p, ref)) for k, c in progs.items()}, repeats)
    last = runs[steps[-1]]
    return [
        {
            "stabilization_steps": n,
            "step_us": best[n] / cfg.n_steps * 1e6,
            "max_violation": float(runs[n].violation.max()),
            "max_theta_diff_rad": float(jnp.max(jnp.abs(runs[n].theta - last.theta))),
        }
        for n in steps
    ]


def scaled_pulses(setup, factors):
    """The config's perturbations at each of ``factors`` times their magnitudes, stacked (one
    leading run axis), through the one pulse builder."""
    specs, h = setup.config.perturbations, setup.config.h
    rows = [
        build_pulses(
            [dataclasses.replace(s, magnitude=s.magnitude * float(f)) for s in specs],
            setup.model,
            h,
            setup.window.index,
        )
        for f in factors
    ]
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *rows)


def batched(setup, sizes, repeats: int, programs: dict | None = None, dtype: str = "float64") -> list[dict]:
    """Total steps per second of a vmap over pulse magnitudes, split over this process's devices
    as a sweep runs it (:func:`~neuromotor.studies.sweep.runner.shard_vmap`; one per core from
    the command line). Where it is split, the same batch on one device is timed too, in
    alternation (``one_device_*``). ``programs`` (a dict) receives each compiled batch as a
    zero-argument callable, keyed ``batch<size>`` (``batch<size>_float32`` for ``dtype =
    "float32"``; ``..._one_device`` for the unsplit twin)."""
    from neuromotor.studies.sweep.runner import AXIS, batch_mesh, shard_vmap

    m, g, ref, cfg = setup.model, setup.gains, setup.ref, setup.options
    out = []
    for size in sizes:
        mags = scaled_pulses(setup, np.linspace(0.5, 1.5, size))
        cfg = dataclasses.replace(
            setup.options,
            solver=solvers.Solver(setup.options.solver).batched() if size > 1 else setup.options.solver,
            dtype=dtype,
        )
        one = lambda pulses, shared, cfg=cfg: (
            dy.simulate(dy.SimModel(m, shared[1], cfg), dy.Params(shared[0], pulses)).theta
        )
        meshes = {"": batch_mesh(size, cfg) if size > 1 else None}
        if meshes[""] is not None:
            meshes["_one_device"] = None
        calls, row = (
            {},
            {
                "batch": size,
                "dtype": dtype,
                "steps": cfg.n_steps,
                "devices": 1 if meshes[""] is None else meshes[""].devices.size,
            },
        )
        for suffix, mesh in meshes.items():
            args = (mags, (g, ref))
            if mesh is not None:  # placed once: the timed calls move nothing
                args = (
                    jax.device_put(mags, NamedSharding(mesh, P(AXIS))),
                    jax.device_put((g, ref), NamedSharding(mesh, P())),
                )
            comp, compile_s = _compile(shard_vmap(one, mesh), *args)
            calls[suffix] = lambda comp=comp, args=args: comp(*args)
            row["compile_s" if not suffix else "one_device_compile_s"] = compile_s
            if programs is not None:
                programs[f"batch{size}" + ("" if dtype == "float64" else f"_{dtype}") + suffix] = calls[suffix]
        best = interleaved(calls, repeats) if len(calls) > 1 else {"": _best(calls[""], repeats)}
        for suffix, t in best.items():
            key = "" if not suffix else "one_device_"
            row.update({f"{key}seconds": t, f"{key}steps_per_s": size * cfg.n_steps / t})
        row["real_time_factor"] = size * cfg.n_steps * cfg.h / row["seconds"]
        out.append(row)
    return out


def gain_jacobian(setup, repeats: int, programs: dict | None = None) -> dict:
    """jacfwd over (ks, kd) through the rollout, against the rollout alone. ``programs`` (a dict)
    receives both compiled programs as zero-argument callables (``jacfwd``, ``jacfwd_rollout``)."""
    from neuromotor.studies.gains import gains_for

    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options

    def theta(x, g, ref):
        return dy.simulate(dy.SimModel(m, ref, cfg), dy.Params(gains_for(g, ks=x[0], kd=x[1]), p)).theta

    x = jnp.stack([g.ks, g.kd])
    fwd, c1 = _compile(theta, x, g, ref)
    jac, c2 = _compile(jax.jacfwd(theta), x, g, ref)
    t_fwd = _best(lambda: fwd(x, g, ref), repeats)
    t_jac = _best(lambda: jac(x, g, ref), repeats)
    if programs is not None:
        programs.update(jacfwd=lambda: jac(x, g, ref), jacfwd_rollout=lambda: fwd(x, g, ref))
    return {
        "seconds_simulated": cfg.n_steps * cfg.h,
        "rollout_s": t_fwd,
        "jacfwd_s": t_jac,
        "ratio": t_jac / t_fwd,
        "compile_rollout_s": c1,
        "compile_jacfwd_s": c2,
    }


def inverse(clips, repeats: int, top: dict | None = None) -> list[dict]:
    """Inverse dynamics (Eq. 3) on every frame of whole clips."""
    out = []
    for clip in clips:
        character, traj = config_character(_clip_config(clip, top))
        times = jnp.asarray(np.arange(character.clip.n_frames) * character.clip.frame_time)
        t = time.perf_counter()
        jax.block_until_ready(inverse_dynamics(character.model, traj, times))
        first = time.perf_counter() - t
        best = _best(lambda: inverse_dynamics(character.model, traj, times), repeats)
        out.append(
            {
                "clip": pathlib.Path(str(character.clip.path)).name,
                "frames": int(times.shape[0]),
                "first_call_s": first,
                "seconds": best,
                "us_per_frame": best / times.shape[0] * 1e6,
            }
        )
    return out


def mujoco_reference(setup, steps: int, repeats: int, ours=None) -> dict | None:
    """MuJoCo on the same skeleton, masses and step (one thread, implicitfast, PD servos).

    ``ours`` (a callable running our compiled rollout of ``setup.options.n_steps`` steps) adds the
    ratio measured interleaved: our rollout and MuJoCo over the same number of steps, in
    alternation, best of each. The host's speed drifts by 2x or more between runs minutes
    apart, so this ratio is steadier than two figures taken at different moments."""
    try:
        import mujoco
    except ImportError:
        return None
    mj, data = mujoco_start(setup.character, setup.options.h, setup.ref.theta[0])
    qpos0, qvel0 = data.qpos.copy(), data.qvel.copy()

    def run(n):
        data.qpos[:] = qpos0
        data.qvel[:] = qvel0
        for _ in range(n):
            mujoco.mj_step(mj, data)
        return np.zeros(())

    t = _best(lambda: run(steps), repeats)
    out = {
        "version": mujoco.__version__,
        "nv": int(mj.nv),
        "nu": int(mj.nu),
        "steps": steps,
        "step_us": t / steps * 1e6,
        "steps_per_s": steps / t,
        "real_time_factor": steps * setup.options.h / t,
    }
    if ours is not None:
        n = setup.options.n_steps
        best = interleaved({"ours": ours, "mujoco": lambda: run(n)}, max(3 * repeats, 10))
        out["interleaved"] = {
            "steps": n,
            "ours_us": best["ours"] / n * 1e6,
            "mujoco_us": best["mujoco"] / n * 1e6,
            "ratio": best["ours"] / best["mujoco"],
        }
    return out


def mujoco_start(character, h: float, theta0):
    """(MjModel, MjData) of the exported MJCF at step ``h``, starting from the joint angles
    ``theta0`` (the mocap's first pose) at rest, held there by the servos (``ctrl``)."""
    import mujoco

    from neuromotor.io.mjcf import model_to_mjcf

    mj = mujoco.MjModel.from_xml_string(model_to_mjcf(character, timestep=h))
    data = mujoco.MjData(mj)
    theta0 = np.asarray(theta0)
    if mj.nq == 7 + theta0.shape[0]:  # hinges are our DOFs, in our order (see mjcf.py)
        data.qpos[7:] = theta0
    data.ctrl[:] = data.qpos[7 : 7 + mj.nu]
    mujoco.mj_forward(mj, data)
    return mj, data


def mjx_beside(setup, batch_setup, programs: dict, res: dict, repeats: int, log=print) -> dict:
    """MuJoCo MJX beside MuJoCo C and ours (:func:`neuromotor.studies.bench_mjx.compare`) on the
    model :func:`mujoco_reference` steps; ``programs``: our compiled rollout, batch and jacfwd.
    Without MJX, one line saying why and ``{"skipped": why}``."""
    from neuromotor.studies import bench_mjx

    why = bench_mjx.unavailable()
    if why is not None:
        log(f"MJX: skipped ({why})")
        return {"skipped": why}
    size = max(r["batch"] for r in res["batch"])
    ours = {
        "rollout": programs["rollout"],
        "batch": programs[f"batch{size}"],
        "jacfwd": programs["jacfwd"],
        "jacfwd_rollout": programs["jacfwd_rollout"],
    }
    if f"batch{size}_float32" in programs:
        ours["batch_float32"] = programs[f"batch{size}_float32"]
    if size > 1 and "batch1" in programs:
        ours["batch_one"] = programs["batch1"]
    if f"batch{size}_one_device" in programs:
        ours["batch_one_device"] = programs[f"batch{size}_one_device"]
    mj, data = mujoco_start(setup.character, setup.options.h, setup.ref.theta[0])
    # MJX gets the XLA options ours is compiled with (on the CPU they cut its jacfwd time ~5x).
    out = bench_mjx.compare(
        mj,
        data,
        ours,
        steps=setup.options.n_steps,
        batch=size,
        batch_steps=batch_setup.options.n_steps,
        rounds=max(2 * repeats, 7),
        compiler_options=compiler.compiler_options() if jax.default_backend() == "cpu" else None,
    )
    out["ours_compile_s"] = {
        "rollout": res["single"]["compile_s"],
        "jacfwd": res["jacfwd"]["compile_jacfwd_s"],
        "batch": next(r["compile_s"] for r in res["batch"] if r["batch"] == size),
    }
    bench_mjx.log_figures(out, log, out["ours_compile_s"])
    return out


def free_root(clip, repeats: int, top: dict | None = None, seconds: float = 1.0) -> dict:
    """One free-standing trajectory on the ground (postural loop on) and the same held pose on the
    driven root without contact, timed in alternation (``top``: the clip's top-level config keys)."""
    from neuromotor.physics.contact import simulate_contact
    from neuromotor.studies.ground import ground_scene
    from neuromotor.studies.standing import standing_setup

    driven = standing_setup(seconds, H, {"enabled": False}, clip=clip, root="driven", top=top)
    free = standing_setup(seconds, H, None, clip=clip, top=top)
    scene = ground_scene(free.ground)
    c_driven, _ = _compile(dy.simulate, driven.sim_model, driven.params)
    c_free, compile_s = _compile(simulate_contact, free.sim_model, free.params, scene)
    runs = {
        "driven": lambda: c_driven(driven.sim_model, driven.params),
        "free": lambda: c_free(free.sim_model, free.params, scene),
    }
    out = runs["free"]()
    best = interleaved(runs, repeats)
    n = free.options.n_steps
    lam = np.asarray(out.contact.normal_impulse)
    return {
        "steps": n,
        "h": H,
        "driven_us": best["driven"] / n * 1e6,
        "free_us": best["free"] / n * 1e6,
        "ratio": best["free"] / best["driven"],
        "free_real_time_factor": H * n / best["free"],
        "driven_real_time_factor": H * n / best["driven"],
        "contacts_mean": float((lam[1:] > 0).sum(-1).mean()),
        "compile_s": compile_s,
    }


def plot_throughput(rows: list[dict], mujoco_sps: float | None, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    sizes = [r["batch"] for r in rows]
    ax.loglog(sizes, [r["steps_per_s"] for r in rows], "o-", label="neuromotor (vmap over the CPU devices)")
    if mujoco_sps:
        ax.axhline(mujoco_sps, color="k", ls="--", label="MuJoCo, one thread")
    ax.axhline(100 / H, color="0.6", ls=":", label="100x real time")
    ax.set_xlabel("batch size (trajectories)")
    ax.set_ylabel("simulated steps per second")
    ax.set_title("19-joint clip, h = 1/120 s, float64")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_all(
    clip=None,
    solver: str = "nullspace",
    sizes=(1, 8, 64, 256),
    batch_seconds: float = 0.25,
    repeats: int = 5,
    idyn_clips=(),
    plot=None,
    log=print,
    dense_too: bool = True,
    mjx: bool = True,
    free: bool = True,
    top: dict | None = None,
) -> dict:
    """Run every benchmark and print the figures as they come (``mjx``: MuJoCo MJX beside
    MuJoCo C, when mujoco-mjx is installed; ``free``: the free root on the ground, ``top`` the
    clip's top-level config keys for it)."""
    log(f"machine: {machine()}")
    res: dict = {"machine": machine()}
    setup = _setup(clip, 1.0, solver, top)
    log(f"model: {setup.model.n_bodies} bodies, {setup.model.n_dofs} DOFs, h = {setup.options.h:.6f} s")
    res["single"], ours = single(setup, repeats)
    _log_single(res["single"], log)
    if dense_too:  # the other solvers, for comparison
        for other in ("tree", "dense"):
            if other != solver:
                res[f"single_{other}"] = single(_setup(clip, 1.0, other, top), max(2, repeats // 2))[0]
                _log_single(res[f"single_{other}"], log)
    res["compiler_options"] = compiler_options_ab(setup, 2 * repeats)
    ab = res["compiler_options"]
    log(
        f"compiler options (interleaved): {ab['tuned_us']:.1f} us/step tuned vs {ab['default_us']:.1f} us/step "
        f"with XLA defaults -> {ab['speedup']:.2f}x; max |theta difference| {ab['max_theta_diff_rad']:.1e} rad"
    )
    res["stabilization"] = stabilization_ab(setup, 2 * repeats)
    for r in res["stabilization"]:
        log(
            f"post-stabilization, {r['stabilization_steps']} Newton step(s): {r['step_us']:.1f} us/step, max violation "
            f"{r['max_violation']:.1e} m, max |theta - theta(2 steps)| {r['max_theta_diff_rad']:.1e} rad"
        )
    programs = {"rollout": ours}  # compiled programs of ours, for the interleaved MJX rounds
    res["jacfwd"] = gain_jacobian(setup, repeats, programs)
    j = res["jacfwd"]
    log(
        f"jacfwd over (ks, kd), {j['seconds_simulated']:.2f} s rollout: {j['jacfwd_s'] * 1e3:.1f} ms vs "
        f"{j['rollout_s'] * 1e3:.1f} ms -> {j['ratio']:.2f}x (compile {j['compile_jacfwd_s']:.1f} s)"
    )
    res["mujoco"] = mujoco_reference(setup, 2000, repeats, ours=ours)
    if res["mujoco"] is None:
        log("MuJoCo: not installed (pip install mujoco); skipped")
    else:
        mj = res["mujoco"]
        log(
            f"MuJoCo {mj['version']}: {mj['step_us']:.1f} us/step, {mj['steps_per_s']:.0f} steps/s, "
            f"RTF {mj['real_time_factor']:.0f}; ours/MuJoCo per-step time: "
            f"{res['single']['step_us'] / mj['step_us']:.2f}x"
        )
        if "interleaved" in mj:
            il = mj["interleaved"]
            log(
                f"interleaved, {il['steps']} steps each: ours {il['ours_us']:.1f} us/step, MuJoCo "
                f"{il['mujoco_us']:.1f} us/step -> ours/MuJoCo {il['ratio']:.2f}x (real-time factor "
                f"{H / il['ours_us'] * 1e6:.0f} at that moment)"
            )
    bsetup = _setup(clip, batch_seconds, solver, top)
    res["batch"] = batched(bsetup, sizes, max(2, repeats // 2), programs)
    res["batch_float32"] = batched(bsetup, [max(sizes)], max(2, repeats // 2), programs, dtype="float32")
    for r in res["batch"] + res["batch_float32"]:
        ratio = "" if res["mujoco"] is None else f" ({r['steps_per_s'] / res['mujoco']['steps_per_s']:.2f}x MuJoCo)"
        split = (
            ""
            if r["devices"] == 1
            else (f" over {r['devices']} devices (one device: {r['one_device_steps_per_s']:.0f} steps/s, interleaved)")
        )
        log(
            f"batch {r['batch']:4d} ({r['dtype']}): {r['steps_per_s']:10.0f} steps/s{ratio}{split}, "
            f"compile {r['compile_s']:.1f} s"
        )
    res["batch_split"] = batch_split(setup, max(sizes), max(2, repeats // 2))
    bs = res["batch_split"]
    mj_us = "" if res["mujoco"] is None else f"; one MuJoCo step {res['mujoco']['step_us']:.1f} us"
    log(
        f"batch {bs['batch']} split (us per trajectory-step): Jacobians {bs['jacobians']:.1f}, KKT solve "
        f"{bs['kkt_solve']:.1f}, post-stabilization {bs['post_stabilization']:.1f}, whole step {bs['step']:.1f}{mj_us}"
    )
    if free:
        res["free_root"] = fr = free_root(clip, 2 * repeats, top)
        log(
            f"free root on the ground, standing (balance on, {fr['contacts_mean']:.1f} contacts a step), interleaved "
            f"with the same pose on the driven root: {fr['free_us']:.0f} vs {fr['driven_us']:.0f} us/step "
            f"({fr['ratio']:.1f}x); real-time factor {fr['free_real_time_factor']:.1f} vs "
            f"{fr['driven_real_time_factor']:.1f} at h = 1/120 s"
        )
    if mjx:
        res["mjx"] = mjx_beside(setup, bsetup, programs, res, repeats, log)
    if idyn_clips:
        res["inverse_dynamics"] = inverse(idyn_clips, repeats, top)
        for r in res["inverse_dynamics"]:
            log(
                f"inverse dynamics {r['clip']}: {r['frames']} frames in {r['seconds'] * 1e3:.1f} ms "
                f"({r['us_per_frame']:.1f} us/frame); first call (compile) {r['first_call_s']:.1f} s"
            )
    if plot:
        plot_throughput(res["batch"], None if res["mujoco"] is None else res["mujoco"]["steps_per_s"], plot)
        log(f"wrote {plot}")
    return res


def _log_single(s: dict, log) -> None:
    sp = s["split_us"]
    log(
        f"[{s['solver']}] one trajectory: {s['step_us']:.1f} us/step, {s['steps_per_s']:.0f} steps/s, "
        f"real-time factor {s['real_time_factor']:.1f}, compile {s['compile_s']:.1f} s"
    )
    log(
        f"[{s['solver']}]   split (us/step): Jacobians {sp['jacobians']:.1f}, KKT solve {sp['kkt_solve']:.1f}, "
        f"post-stabilization {sp['post_stabilization']:.1f}, rest {sp['rest']:.1f}"
    )


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(ap)
    return run_from_args(ap.parse_args(argv))


def add_arguments(ap) -> None:
    ap.add_argument("clip", nargs="?", default=None, help="BVH clip (default: the embedded 19-joint clip)")
    ap.add_argument("--solver", choices=("nullspace", "tree", "dense"), default="nullspace")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 8, 64, 256])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--idyn", nargs="*", default=[], help="clips for the inverse-dynamics figure")
    ap.add_argument("--plot", default=None, help="PNG of throughput against batch size")
    ap.add_argument("--json", default=None, help="write all figures as JSON")
    ap.add_argument("--no-dense", action="store_true", help="skip the other solvers (tree, dense reference)")
    ap.add_argument("--no-mjx", action="store_true", help="skip MuJoCo MJX (compiles six programs)")
    ap.add_argument("--no-free", action="store_true", help="skip the free root on the ground (issue 38)")
    ap.add_argument("--free-only", action="store_true", help="only the free root on the ground beside the driven one")


def run_from_args(args) -> int:
    top = None
    if hasattr(args, "units"):  # the command line's clip options, as a config's top-level keys
        top = {
            k: v
            for k, v in dict(
                units=args.units,
                up_axis=args.up_axis,
                stature=args.stature,
                body_mass=args.body_mass,
                sex=args.sex,
                simulate_extremities=args.simulate_extremities,
            ).items()
            if v is not None
        }
    if getattr(args, "free_only", False):
        print(f"machine: {machine()}")
        fr = free_root(args.clip, 2 * args.repeats, top)
        print(
            f"free root on the ground, standing: {fr['free_us']:.0f} us/step, driven root (same pose): "
            f"{fr['driven_us']:.0f} us/step ({fr['ratio']:.1f}x); real-time factor {fr['free_real_time_factor']:.1f} "
            f"vs {fr['driven_real_time_factor']:.1f} at h = 1/120 s; {fr['contacts_mean']:.1f} contacts a step"
        )
        if args.json:
            pathlib.Path(args.json).write_text(
                json.dumps({"machine": machine(), "free_root": fr}, indent=2, default=float)
            )
        return 0
    res = run_all(
        args.clip,
        args.solver,
        tuple(args.sizes),
        repeats=args.repeats,
        idyn_clips=tuple(args.idyn),
        plot=args.plot,
        dense_too=not args.no_dense,
        mjx=not getattr(args, "no_mjx", False),
        free=not getattr(args, "no_free", False),
        top=top,
    )
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(res, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
