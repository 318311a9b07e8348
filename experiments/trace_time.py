"""Trace (lowering) and compile time of a rollout and of its jacfwd, grad and vmap, with the
scan's carry started as depending on the parameters (``dynamics.depending_on``) and without.

    .venv/bin/python experiments/trace_time.py [--seconds 0.5] [--rounds 2]

Each round lowers and compiles every program both ways, alternating, with the persistent compile
cache off; the best of the rounds is printed. The two ways must give equal programs: the script
checks that their outputs are equal bit for bit.
"""

import argparse
import dataclasses
import time

import _common  # noqa: F401
import jax
import jax.numpy as jnp
import numpy as np

from neuromotor import compiler
from neuromotor.physics import dynamics
from neuromotor.studies import bench


def programs(seconds: float):
    s = bench._setup(None, seconds, "nullspace")

    def theta(x):
        g = dataclasses.replace(s.gains, ks=jnp.exp(x[0]), kd=jnp.exp(x[1]))
        return dynamics.rollout(s.model, g, s.pulses, s.ref, s.options).theta

    def sweep(mags):
        one = lambda m: dynamics.rollout(s.model, s.gains, dataclasses.replace(s.pulses, magnitude=m), s.ref, s.options)
        return jax.vmap(lambda m: one(m).theta)(mags)

    x = jnp.log(jnp.array([400.0, 20.0]))
    mags = jnp.linspace(0.5, 1.5, 8)[:, None] * s.pulses.magnitude[None]
    return {"rollout": (theta, x), "jacfwd": (jax.jacfwd(theta), x),
            "grad": (jax.grad(lambda x: jnp.sum(theta(x) ** 2)), x), "vmap 8": (sweep, mags)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=0.5)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    jax.config.update("jax_enable_compilation_cache", False)
    tied = dynamics.depending_on
    ways = {"tied": tied, "untied": lambda params, carry, skip=None: carry}
    progs = programs(args.seconds)  # built once; each round traces them afresh
    best: dict = {}
    outs: dict = {}
    for r in range(args.rounds):
        for way in (ways if r % 2 == 0 else dict(reversed(ways.items()))):
            dynamics.depending_on = ways[way]
            jax.clear_caches()  # no trace of the other way is reused
            for name, (fn, arg) in progs.items():
                t0 = time.perf_counter()
                low = compiler.jit(fn).lower(arg)
                t1 = time.perf_counter()
                exe = low.compile()
                t2 = time.perf_counter()
                outs[way, name] = np.asarray(exe(arg))
                old = best.get((way, name), (np.inf, np.inf))
                best[way, name] = (min(old[0], t1 - t0), min(old[1], t2 - t1))
    dynamics.depending_on = tied
    print(f"{args.seconds} s rollout, best of {args.rounds} rounds; lower / compile, seconds")
    for name in progs:
        (lt, ct), (lu, cu) = best["tied", name], best["untied", name]
        same = np.array_equal(outs["tied", name], outs["untied", name])
        print(f"{name:8s} tied {lt:5.1f} / {ct:5.1f}   untied {lu:5.1f} / {cu:5.1f}   untied/tied lower time {lu / lt:.2f}, "
              f"outputs {'equal bit for bit' if same else 'DIFFER'}")


if __name__ == "__main__":
    main()
