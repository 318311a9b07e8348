"""Benchmark: the step with and without an active ball contact.

    .venv/bin/python experiments/bench_contact.py [--steps 120] [--repeats 3]

On the embedded clip (19 bodies), it times whole jitted rollouts (one lax.scan) and prints the
milliseconds per step after compilation (the best of the interleaved repeats) and the time of
the first call (compilation included):

* the contact-free step of dynamics (no ball), null-space and dense solvers, for reference;
* contact step, ball never launched (no contact is ever active);
* contact step, ball resting on the ground (an active contact at every step);
* contact step, ball thrown at the chest (an impact and a bounce on the ground), with the
  null-space solver (the default) and with the dense one.

The contact step is the ordinary step's stages plus the contact rows: it always runs the whole
LCP path (fixed PGS sweeps, masked contacts), so it costs the same with and without an active
contact; what it adds over the ordinary step is the solver's responses to unit contact
impulses (extra right-hand sides, one factorization), the candidate search and the PGS sweeps.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from neuromotor.config import simulation_config  # noqa: E402
from neuromotor.physics import contact as ct  # noqa: E402
from neuromotor.physics.dynamics import Params, SimModel  # noqa: E402
from neuromotor.studies.simulate import _zero, prepare, simulate_jit  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=120)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    h = 1.0 / 120.0
    data = {"sim": {"start": 0.95, "duration": args.steps * h},
            "ball": {"radius": 0.11, "mass": 1.0, "position": [-0.45, 1.45, 4.5], "speed": 14.0,
                     "target": "Chest2", "launch": 1.0, "restitution": 0.6, "friction": 0.5}}
    setup = prepare(simulation_config(data, "<bench>"))
    model, bs = setup.model, setup.ball
    nopulse = _zero(setup.pulses)
    dense = dataclasses.replace(setup.options, solver="dense")
    # Same dtypes and weak types as the thrown ball, so all contact cases share one compile.
    resting = eqx.tree_at(lambda b: (b.position, b.speed, b.launch), bs.ball,
                          (bs.ball.position.at[:].set(jnp.array([2.0, float(bs.ball.radius), 0.0])),
                           jnp.zeros_like(bs.ball.speed), jnp.zeros_like(bs.ball.launch)))
    sim, sim_dense, params = setup.sim_model, SimModel(model, setup.ref, dense), Params(setup.gains, nopulse)
    cases = {
        "dynamics step, null-space solver (no ball)": lambda: simulate_jit(sim, params),
        "dynamics step, dense solver (no ball)": lambda: simulate_jit(sim_dense, params),
        "contact step, no active contact": lambda: ct.simulate_contact_jit(sim, params,
                                                                           bs.scene(ct.never_launched(bs.ball))),
        "contact step, active contact every step": lambda: ct.simulate_contact_jit(sim, params, bs.scene(resting)),
        "contact step, ball hits the chest": lambda: ct.simulate_contact_jit(sim, params, bs.scene()),
        "contact step, ball hits the chest, dense": lambda: ct.simulate_contact_jit(sim_dense, params, bs.scene()),
    }
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, "
          f"jax {jax.__version__} on {jax.default_backend()}, float64")
    print(f"model: {model.n_bodies} bodies, {len(bs.capsules.names)} capsules + ground, "
          f"max_contacts {bs.settings.max_contacts}, {bs.settings.pgs_iterations} PGS sweeps, "
          f"{args.steps} steps of h = 1/120 s")
    first = {}
    for name, fn in cases.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first[name] = time.perf_counter() - t0
    # Interleave the repeats so that load from other processes hits every case alike.
    best = {name: np.inf for name in cases}
    for _ in range(args.repeats):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            best[name] = min(best[name], time.perf_counter() - t0)
    for name, fn in cases.items():
        out = fn()
        extra = ""
        if isinstance(out, ct.ContactRollout):
            active = np.asarray(out.contact.active).any(-1)[1:]
            extra = f"  (steps with an active contact: {int(active.sum())}/{args.steps})"
        print(f"{name:42s} {1e3 * best[name] / args.steps:8.3f} ms/step   first call {first[name]:6.1f} s{extra}")


if __name__ == "__main__":
    main()
