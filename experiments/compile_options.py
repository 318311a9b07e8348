"""Cold compile seconds of the package's programs with XLA:CPU's defaults and with
``neuromotor.compiler``'s options (every program is built by ``compiler.jit``; docs/benchmarks.md,
"Issue 17: the CPU options for every program").

    .venv/bin/python experiments/compile_options.py [--clip FILE] [--rounds 2]

Each program is lowered and compiled in alternation, ``--rounds`` times each way, without the
persistent cache; the best of each is printed with the ratio.
"""

import argparse
import time

import _common  # noqa: F401,E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from neuromotor import compiler  # noqa: E402
from neuromotor.physics import dynamics as dy  # noqa: E402
from neuromotor.physics.inverse import inverse_dynamics  # noqa: E402
from neuromotor.studies import bench  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default=None, help="BVH file (default: the embedded clip)")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    jax.config.update("jax_enable_compilation_cache", False)
    setup = bench._setup(args.clip, 1.0, "nullspace")
    m, traj, g, p, ref, cfg = setup.model, setup.traj, setup.gains, setup.pulses, setup.ref, setup.options
    t0 = jnp.asarray(float(ref.time[0]))
    times = ref.time
    programs = {
        "reference grid (discrete inverse included)": (lambda m, tr, t0: dy._make_reference.__wrapped__(m, tr, t0, cfg),
                                                       (m, traj, t0)),
        "inverse dynamics of the grid": (inverse_dynamics.__wrapped__, (m, traj, times)),
        "rollout (1 s)": (lambda m, g, p, ref: dy.rollout(m, g, p, ref, cfg), (m, g, p, ref)),
    }
    print(f"{'program':34s} {'XLA defaults':>13s} {'tuned':>8s} {'ratio':>6s}")
    for name, (fn, fargs) in programs.items():
        best = {"default": float("inf"), "tuned": float("inf")}
        for _ in range(args.rounds):
            for kind, opts in (("default", None), ("tuned", compiler.compiler_options() or None)):
                # A fresh wrapper each time: JAX keeps compiled programs of a Lowered in memory.
                lowered = jax.jit(lambda *a, fn=fn: fn(*a)).lower(*fargs)
                t = time.perf_counter()
                lowered.compile(compiler_options=opts)
                best[kind] = min(best[kind], time.perf_counter() - t)
        print(f"{name:34s} {best['default']:12.2f}s {best['tuned']:7.2f}s {best['default'] / best['tuned']:5.2f}x",
              flush=True)


if __name__ == "__main__":
    main()
