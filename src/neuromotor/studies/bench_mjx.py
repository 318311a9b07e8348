"""MuJoCo MJX beside MuJoCo C and ours in ``neuromotor bench`` (optional: ``pip install
'neuromotor[mjx]'``, which brings ``mujoco-mjx``).

MJX steps the very model MuJoCo C steps: the exported MJCF
(:func:`neuromotor.io.mjcf.model_to_mjcf`: same skeleton, masses and time step h, implicitfast,
one PD position servo per hinge holding the clip's first pose), moved to JAX by
``mjx.put_model``/``mjx.put_data`` with MJX's pure-JAX implementation (``impl="jax"``). For
float64 and for float32 it compiles three programs and times them:

* one trajectory: ``jit`` of a ``lax.scan`` of ``mjx.step`` that emits ``qpos`` every step (as our
  rollout emits the joint angles);
* a batch: ``vmap`` of that trajectory over perturbed initial velocities;
* ``jax.jacfwd`` of the trajectory over two servo gain scales (kp, kv), against the trajectory;

and the cold compile seconds of each. float32 casts the floating leaves of the MJX Model and
Data and traces its programs with ``jax.enable_x64(False)`` in scope only, so MJX's own constants
stay float32 as they would for an MJX user (the process keeps x64; our physics is untouched).

The host's speed drifts by 2x within minutes, so the engines are timed in rounds: every round runs
each program once (ours, MJX float64, MJX float32, MuJoCo C on one thread), the order reversed in
every other round, and each ratio is the median over rounds of that round's ratio.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

DTYPES = ("float64", "float32")
# Initial velocities of the batch: the start state's plus this much (rad/s, m/s) of Gaussian noise.
BATCH_VELOCITY_NOISE = 0.2
INSTALL_HINT = "pip install 'neuromotor[mjx]'"


def _import_mjx():
    # mujoco.mjx prints a line when its optional Warp backend is absent; that is not news here.
    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


def unavailable() -> str | None:
    """Why MJX cannot run here, in one line (None when it can)."""
    try:
        _import_mjx()
    except ImportError as e:
        return f"mujoco-mjx is not installed ({e}); {INSTALL_HINT}"
    except Exception as e:  # an MJX that does not match the installed MuJoCo fails at import
        return f"mujoco-mjx does not import: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    return None


def cast(tree, dtype):
    """``tree`` with its floating leaves in ``dtype`` (integer and boolean leaves kept)."""
    return jax.tree_util.tree_map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


def put(mj, d0, dtype: str = "float64"):
    """(MJX Model, MJX Data) of a MuJoCo model and start state, floating leaves in ``dtype``."""
    mjx = _import_mjx()
    return cast(mjx.put_model(mj, impl="jax"), dtype), cast(mjx.put_data(mj, d0, impl="jax"), dtype)


def with_gains(m, x):
    """``m`` with every position servo's kp scaled by ``x[0]`` and kv by ``x[1]``. A position
    actuator's force is ``gainprm[0] ctrl + biasprm[1] q + biasprm[2] qdot`` with
    ``gainprm[0] = kp = -biasprm[1]`` and ``biasprm[2] = -kv``."""
    gain = m.actuator_gainprm.at[:, 0].multiply(x[0])
    bias = m.actuator_biasprm.at[:, 1].multiply(x[0]).at[:, 2].multiply(x[1])
    return m.replace(actuator_gainprm=gain, actuator_biasprm=bias)


def trajectory(steps: int) -> Callable:
    """``f(x, m, d) -> qpos (steps, nq)``: ``steps`` MJX steps from ``d`` with gain scales ``x``."""
    mjx = _import_mjx()

    def run(x, m, d):
        m = with_gains(m, x)

        def body(d, _):
            d = mjx.step(m, d)
            return d, d.qpos

        return jax.lax.scan(body, d, None, length=steps)[1]

    return run


def compile_in(fn, args, dtype: str, compiler_options: dict | None = None):
    """(compiled, cold compile seconds); float32 is traced with x64 off so constants stay float32.
    ``compiler_options``: XLA's, None for its defaults (as an MJX user compiles)."""
    t = time.perf_counter()
    with jax.enable_x64(dtype == "float64"):
        compiled = jax.jit(fn).lower(*args).compile(compiler_options=compiler_options)
    return compiled, time.perf_counter() - t


def programs(
    mj, d0, dtype: str, steps: int, batch: int, batch_steps: int, seed: int = 0, compiler_options: dict | None = None
):
    """MJX's three programs in ``dtype`` as zero-argument callables (``rollout``, ``batch``,
    ``jacfwd``), their cold compile seconds, and the trajectory's last ``qpos`` (float64 numpy)."""
    m, d = put(mj, d0, dtype)
    x = jnp.ones(2, dtype)
    noise = np.random.default_rng(seed).standard_normal((batch, mj.nv)) * BATCH_VELOCITY_NOISE
    qvels = jnp.asarray(np.asarray(d0.qvel)[None] + noise, dtype)
    one, short = trajectory(steps), trajectory(batch_steps)

    def many(x, m, d, qvels):
        return jax.vmap(lambda qv: short(x, m, d.replace(qvel=qv)))(qvels)

    built, compile_s = {}, {}
    for name, fn, args in (
        ("rollout", one, (x, m, d)),
        ("batch", many, (x, m, d, qvels)),
        ("jacfwd", jax.jacfwd(one), (x, m, d)),
    ):
        compiled, compile_s[name] = compile_in(fn, args, dtype, compiler_options)
        built[name] = lambda compiled=compiled, args=args: compiled(*args)
    last = np.asarray(built["rollout"]()[-1], np.float64)
    return built, compile_s, last


def c_rollout(mj, d0, steps: int) -> tuple[Callable, np.ndarray]:
    """MuJoCo C from ``d0`` for ``steps`` steps on one thread, as a zero-argument callable, and
    the ``qpos`` it ends at."""
    import mujoco

    data = mujoco.MjData(mj)

    def run():
        data.qpos[:], data.qvel[:], data.ctrl[:] = d0.qpos, d0.qvel, d0.ctrl
        for _ in range(steps):
            mujoco.mj_step(mj, data)
        return data.qpos

    return run, run().copy()


def timed_rounds(progs: dict[str, Callable], rounds: int) -> dict[str, np.ndarray]:
    """Wall seconds of every program in each of ``rounds`` rounds, each round running every
    program once, in reverse order every other round (after one untimed warm-up call each)."""
    names = list(progs)
    for name in names:
        jax.block_until_ready(progs[name]())
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            t = time.perf_counter()
            jax.block_until_ready(progs[name]())
            times[name].append(time.perf_counter() - t)
    return {name: np.asarray(v) for name, v in times.items()}


def _median(a) -> float:
    return float(np.median(a))


def _figures(t: dict, key: str, steps: int, batch: int, batch_steps: int) -> dict:
    """Medians over rounds for one engine (``key`` prefix of its program names)."""
    out = {
        "step_us": _median(t[f"{key}.rollout"]) / steps * 1e6,
        "batch_steps_per_s": batch * batch_steps / _median(t[f"{key}.batch"]),
    }
    if f"{key}.jacfwd" in t:
        out["jacfwd_over_rollout"] = _median(t[f"{key}.jacfwd"] / t[f"{key}.jacfwd_rollout"])
    if f"{key}.batch_float32" in t:
        out["batch_float32_steps_per_s"] = batch * batch_steps / _median(t[f"{key}.batch_float32"])
    if f"{key}.batch_one_device" in t:
        out["batch_one_device_steps_per_s"] = batch * batch_steps / _median(t[f"{key}.batch_one_device"])
    if f"{key}.batch_one" in t:  # a trajectory-step in the batch over one in a batch of 1, per round
        out["batch_over_one"] = _median(t[f"{key}.batch"] / batch / t[f"{key}.batch_one"])
    return out


def _ratios(t: dict, dtype: str, steps: int, batch: int, batch_steps: int) -> dict:
    """Per-round ratios, median: MJX against MuJoCo C and ours against MJX. Time ratios for the
    trajectory and jacfwd (above 1: the first is slower), throughput ratios for the batch."""
    mjx, c_step = f"mjx_{dtype}", t["c.rollout"] / steps
    out = {
        "mjx_over_c": {
            "step_time": _median(t[f"{mjx}.rollout"] / steps / c_step),
            "batch_throughput": _median(c_step * batch * batch_steps / t[f"{mjx}.batch"]),
        }
    }
    ours = {}
    if "ours.rollout" in t:
        ours["step_time"] = _median(t["ours.rollout"] / t[f"{mjx}.rollout"])
    if "ours.batch" in t:
        ours["batch_throughput"] = _median(t[f"{mjx}.batch"] / t["ours.batch"])
    if "ours.batch_one_device" in t:  # ours unsplit: one device, like MJX's vmap
        ours["batch_throughput_one_device"] = _median(t[f"{mjx}.batch"] / t["ours.batch_one_device"])
    if f"ours.batch_{dtype}" in t:  # ours in the same precision as this MJX
        ours["batch_throughput_same_dtype"] = _median(t[f"{mjx}.batch"] / t[f"ours.batch_{dtype}"])
    if "ours.jacfwd" in t:
        ours["jacfwd_time"] = _median(t["ours.jacfwd"] / t[f"{mjx}.jacfwd"])
    out["ours_over_mjx"] = ours
    return out


def compare(
    mj,
    d0,
    ours: dict[str, Callable],
    steps: int,
    batch: int,
    batch_steps: int,
    rounds: int,
    dtypes=DTYPES,
    compiler_options: dict | None = None,
) -> dict:
    """MJX in each of ``dtypes`` beside MuJoCo C and ``ours``, timed in interleaved rounds.

    ``mj``, ``d0``: the MuJoCo model and its start state (``mj_forward`` done, ``ctrl`` set).
    ``ours``: zero-argument callables, any of ``rollout`` (one trajectory of ``steps`` steps),
    ``batch`` (``batch`` trajectories of ``batch_steps`` steps), ``jacfwd`` and
    ``jacfwd_rollout`` (jacfwd over two gains of a ``steps``-step trajectory, and that
    trajectory), ``batch_float32`` (the batch in float32), ``batch_one`` (one trajectory of
    ``batch_steps`` steps in the batch's program shape), ``batch_one_device`` (the batch on one
    device where ``batch`` is split over several). Returns the medians per engine, the
    ratios, MJX's compile seconds and its largest ``qpos`` difference from MuJoCo C after
    ``steps`` steps. ``compiler_options``: XLA's
    for MJX's programs (None: XLA's defaults, as an MJX user compiles)."""
    import mujoco

    c_run, c_last = c_rollout(mj, d0, steps)
    progs = {f"ours.{k}": fn for k, fn in ours.items()}
    progs["c.rollout"] = c_run
    out = {
        "version": importlib.metadata.version("mujoco-mjx"),
        "mujoco_version": mujoco.__version__,
        "impl": "jax",
        "compiler_options": dict(compiler_options or {}),
        "nv": int(mj.nv),
        "nu": int(mj.nu),
        "h": float(mj.opt.timestep),
        "steps": steps,
        "batch": batch,
        "batch_steps": batch_steps,
        "rounds": rounds,
    }
    for dtype in dtypes:
        built, compile_s, last = programs(mj, d0, dtype, steps, batch, batch_steps, compiler_options=compiler_options)
        progs.update({f"mjx_{dtype}.{k}": fn for k, fn in built.items()})
        progs[f"mjx_{dtype}.jacfwd_rollout"] = built["rollout"]
        out[dtype] = {"compile_s": compile_s, "max_qpos_diff_vs_c": float(np.max(np.abs(last - c_last)))}
    t = timed_rounds(progs, rounds)
    out["c"] = {"step_us": _median(t["c.rollout"]) / steps * 1e6, "steps_per_s": steps / _median(t["c.rollout"])}
    if {"ours.rollout", "ours.batch"} <= set(t):
        out["ours"] = _figures(t, "ours", steps, batch, batch_steps)
    for dtype in dtypes:
        out[dtype].update(_figures(t, f"mjx_{dtype}", steps, batch, batch_steps))
        out[dtype].update(_ratios(t, dtype, steps, batch, batch_steps))
    return out


def log_figures(r: dict, log=print, ours_compile: dict | None = None) -> None:
    """Print :func:`compare`'s figures, one line per measure."""
    dts, nan = [d for d in DTYPES if d in r], float("nan")
    ours, c = r.get("ours", {}), r["c"]
    ratio = lambda key, sub: ", ".join(f"{r[d][key].get(sub, nan):.2f} ({d})" for d in dts)
    mjx = lambda field, fmt: ", ".join(f"{format(r[d][field], fmt)} ({d})" for d in dts)
    xla = "XLA options as ours" if r.get("compiler_options") else "XLA defaults"
    log(
        f"MJX {r['version']} (impl {r['impl']}, {xla}; the exported MJCF, h = {r['h']:.6f} s, {r['nu']} servos) "
        f"beside MuJoCo C {r['mujoco_version']}, {r['rounds']} interleaved rounds, medians of per-round ratios:"
    )
    log(
        f"  one trajectory ({r['steps']} steps), us/step: ours {ours.get('step_us', nan):.1f}, "
        f"MJX {mjx('step_us', '.1f')}, MuJoCo C {c['step_us']:.1f}; time ours/MJX {ratio('ours_over_mjx', 'step_time')}"
        f"; time MJX/C {ratio('mjx_over_c', 'step_time')}"
    )
    log(
        f"  batch {r['batch']} x {r['batch_steps']} steps, steps/s: ours {ours.get('batch_steps_per_s', nan):.0f}, "
        f"MJX {mjx('batch_steps_per_s', '.0f')}, MuJoCo C one thread {c['steps_per_s']:.0f}; throughput ours/MJX "
        f"{ratio('ours_over_mjx', 'batch_throughput')}; throughput MJX/C {ratio('mjx_over_c', 'batch_throughput')}; "
        f"ours/C {ours.get('batch_steps_per_s', nan) / c['steps_per_s']:.2f}"
    )
    if "batch_one_device_steps_per_s" in ours:
        log(
            f"  ours on one device (the batch unsplit, as MJX's vmap runs): {ours['batch_one_device_steps_per_s']:.0f} "
            f"steps/s; throughput ours/MJX {ratio('ours_over_mjx', 'batch_throughput_one_device')}"
        )
    if "batch_over_one" in ours:
        log(
            f"  a trajectory-step in the batch of {r['batch']} costs {ours['batch_over_one']:.2f} of one in a "
            "batch of 1 (interleaved)"
        )
    if "batch_float32_steps_per_s" in ours and "float32" in r:
        log(
            f"  batch in float32, steps/s: ours {ours['batch_float32_steps_per_s']:.0f}, MJX "
            f"{r['float32']['batch_steps_per_s']:.0f}; throughput ours/MJX "
            f"{r['float32']['ours_over_mjx'].get('batch_throughput_same_dtype', nan):.2f}"
        )
    if "jacfwd_over_rollout" in ours:
        log(
            f"  jacfwd over 2 gains / rollout ({r['steps']} steps): ours {ours['jacfwd_over_rollout']:.2f}x, "
            f"MJX {mjx('jacfwd_over_rollout', '.2f')}; jacfwd time ours/MJX {ratio('ours_over_mjx', 'jacfwd_time')}"
        )
    comp = lambda cs: " / ".join(f"{cs[k]:.1f}" for k in ("rollout", "batch", "jacfwd"))
    ours_c = f"ours {comp(ours_compile)}, " if ours_compile else ""
    log(
        f"  cold compile s (rollout / batch / jacfwd): {ours_c}"
        + ", ".join(f"MJX {comp(r[d]['compile_s'])} ({d})" for d in dts)
    )
    log(
        f"  MJX vs MuJoCo C after {r['steps']} steps, max |qpos difference|: "
        + ", ".join(f"{r[d]['max_qpos_diff_vs_c']:.1e} ({d})" for d in dts)
    )
