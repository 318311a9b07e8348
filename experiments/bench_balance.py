"""Cost of the free-root step on the ground (issue 38) beside the driven step (the paper's).

    taskset -c 0 env XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \\
        .venv/bin/python experiments/bench_balance.py [--seconds 2] [--h 0.008333] [--breakdown]

The clip's most upright frame held still, h = 1/120 s by default: (a) the driven root without
contact (the paper), (b) the free root on the ground with the postural loop (balance), (c) the
same without the loop. ``--breakdown`` adds (b) with one PGS sweep a step and (b) with 8
contacts kept instead of 16, whose differences from (b) are the sweeps' and the contacts'
share of the step. Every variant is compiled first, then timed in interleaved rounds (one run
of each per round, so the host's drift reaches them alike); prints the best round's time per
step and the real-time factor.
"""

from __future__ import annotations

import argparse

import _common  # noqa: F401  (float64, compile cache)
import jax

from neuromotor import compiler
from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.physics.dynamics import simulate
from neuromotor.studies.bench import interleaved
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.standing import standing_setup


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--h", type=float, default=1.0 / 120.0)
    ap.add_argument("--max-contacts", type=int, default=None, help="[ground] max_contacts (default 16)")
    ap.add_argument("--pgs-iterations", type=int, default=None, help="[ground] pgs_iterations (default 40)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds, at least 5 (best kept)")
    ap.add_argument("--breakdown", action="store_true", help="add 1-sweep and 8-contact variants")
    args = ap.parse_args()
    n = int(round(args.seconds / args.h))
    sim_jit = compiler.jit(simulate)
    fns = {}
    driven = standing_setup(args.seconds, args.h, {"enabled": False}, root="driven")
    fns["driven root, no contact (paper)"] = lambda: sim_jit(driven.sim_model, driven.params)
    base = {"max_contacts": args.max_contacts, "pgs_iterations": args.pgs_iterations}
    base = {key: v for key, v in base.items() if v is not None}
    runs = [("free root + ground + balance", None, base), ("free root + ground, no balance", {"enabled": False}, base)]
    if args.breakdown:
        runs += [
            ("  same with balance, 1 PGS sweep", None, {**base, "pgs_iterations": 1}),
            ("  same with balance, 8 contacts", None, {**base, "max_contacts": 8}),
        ]
    for label, bal, ground in runs:
        s = standing_setup(args.seconds, args.h, bal, ground=ground or None)
        scene = ground_scene(s.ground)
        fns[label] = lambda s=s, scene=scene: simulate_contact_jit(s.sim_model, s.params, scene)
    for fn in fns.values():  # compiled before any timing
        jax.block_until_ready(fn())
    rounds = max(args.rounds, 5)  # bench.interleaved's floor
    best = interleaved(fns, rounds)
    print(f"{n} steps at h = {args.h:.6g} s ({args.seconds:g} s simulated), best of {rounds} interleaved rounds")
    for label, wall in best.items():
        print(f"  {label:34s} {1e3 * wall / n:7.3f} ms/step  {args.seconds / wall:7.1f}x real time")


if __name__ == "__main__":
    main()
