"""Cost of the free-root step on the ground (issue 38) beside the driven step (the paper's).

    taskset -c 0 env XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \\
        .venv/bin/python experiments/bench_balance.py [--seconds 2] [--h 0.008333]

The clip's most upright frame held still, h = 1/120 s by default: (a) the driven root without
contact (the paper), (b) the free root on the ground with the postural loop (balance), (c) the
same without the loop. Prints the time per step (best of 3, after compilation) and the
real-time factor.
"""

from __future__ import annotations

import argparse
import time

import _common  # noqa: F401  (float64, compile cache)
import jax

from neuromotor import compiler
from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.physics.dynamics import simulate
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.standing import standing_setup


def best(fn, repeats: int = 3) -> float:
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--h", type=float, default=1.0 / 120.0)
    ap.add_argument("--max-contacts", type=int, default=None, help="[ground] max_contacts (default 16)")
    ap.add_argument("--pgs-iterations", type=int, default=None, help="[ground] pgs_iterations (default 40)")
    args = ap.parse_args()
    n = int(round(args.seconds / args.h))
    sim_jit = compiler.jit(simulate)
    rows = []
    driven = standing_setup(args.seconds, args.h, {"enabled": False}, root="driven")
    rows.append(("driven root, no contact (paper)", best(lambda: sim_jit(driven.sim_model, driven.params))))
    for label, bal in (("free root + ground + balance", None), ("free root + ground, no balance", {"enabled": False})):
        ground = {"max_contacts": args.max_contacts, "pgs_iterations": args.pgs_iterations}
        ground = {key: v for key, v in ground.items() if v is not None} or None
        s = standing_setup(args.seconds, args.h, bal, ground=ground)
        scene = ground_scene(s.ground)
        rows.append((label, best(lambda s=s, scene=scene: simulate_contact_jit(s.sim_model, s.params, scene))))
    print(f"{n} steps at h = {args.h:.6g} s ({args.seconds:g} s simulated), best of 3 after compilation")
    for label, wall in rows:
        print(f"  {label:34s} {1e3 * wall / n:7.3f} ms/step  {args.seconds / wall:7.1f}x real time")


if __name__ == "__main__":
    main()
