"""Quiet standing with the postural loop (issue 38): a still posture from the shipped clip (the
anatomy's most upright frame), free root, ground, no assist.

    .venv/bin/python experiments/stand_balance.py [--seconds 10] [--h 0.008333] [--no-balance]

Prints whether it fell (and when, which body), the COM sway (RMS and range, mm, about its mean,
horizontal) and the run's wall time and real-time factor (after compilation).
"""

from __future__ import annotations

import argparse
import time

import _common  # noqa: F401  (float64, compile cache)
import jax
import numpy as np

from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.studies.balance import balance_metrics
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.standing import standing_setup


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--h", type=float, default=1.0 / 120.0)
    ap.add_argument("--assist", type=float, default=0.0)
    ap.add_argument("--no-balance", action="store_true")
    args = ap.parse_args()
    balance = {"enabled": not args.no_balance, "assist": args.assist}
    setup = standing_setup(args.seconds, args.h, balance)
    scene = ground_scene(setup.ground)
    t0 = time.perf_counter()
    out = simulate_contact_jit(setup.sim_model, setup.params, scene)
    jax.block_until_ready(out)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = simulate_contact_jit(setup.sim_model, setup.params, scene)
    jax.block_until_ready(out)
    wall = time.perf_counter() - t0
    m = balance_metrics(setup, out)
    print(f"still frame at t = {setup.config.still:.3f} s, h = {args.h:.6g} s, {args.seconds:g} s simulated")
    for k, v in m.items():
        print(f"  {k}: {v}")
    model = setup.model
    mass = np.asarray(model.mass)
    com = np.einsum("b,tbi->ti", mass / mass.sum(), np.asarray(out.run.states.pos))
    step = int(round(1.0 / args.h))
    for k in range(0, com.shape[0], step):
        d = 1000 * (com[k] - com[0])
        print(f"  t {k * args.h:5.2f} s  COM moved ({d[0]:7.1f}, {d[1]:7.1f}, {d[2]:7.1f}) mm")
    print(f"wall {wall:.2f} s after compile ({first:.1f} s with compile): {args.seconds / wall:.1f}x real time")


if __name__ == "__main__":
    main()
