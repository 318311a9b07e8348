"""Thread hand-offs of XLA:CPU's runtime in one free-standing run, as the command line starts JAX.

    .venv/bin/python experiments/thread_handoffs.py [--rounds 2] [--seconds 2]

Each round runs two fresh processes one after the other: ``single`` starts JAX as
``neuromotor simulate`` does for a free root (``compiler.one_runtime_thread`` and
``compiler.use_cpu_cores(split=False)``: one device, one runtime thread) and ``per-core`` as it
did before 2026-12-07 (one device per core, XLA's default thread pool). Each compiles the
free-standing run (the clip's upright frame on the ground with the postural loop, h = 1/120 s)
and the same pose on the driven root, then prints the best of three runs per step and the
voluntary context switches of all its threads per step (a thread that sleeps until kernels
handed to another thread are done). Run it once on an idle machine and once with the other
cores busy (``yes > /dev/null &``): the hand-offs cost most there.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import time


def _switches() -> int:
    total = 0
    for status in glob.glob("/proc/self/task/*/status"):
        try:
            with open(status) as f:
                total += sum(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))
        except OSError:  # a thread that ended meanwhile
            pass
    return total


def child(mode: str, seconds: float) -> None:
    import _common  # noqa: F401  (float64, compile cache)

    from neuromotor import compiler

    # PJRT_NPROC="" in the per-core child's environment: XLA's default pool (the old start-up).
    if mode == "single":
        compiler.one_runtime_thread()
    compiler.use_cpu_cores(split=mode != "single")
    import jax

    from neuromotor.physics.contact import simulate_contact_jit
    from neuromotor.physics.dynamics import simulate
    from neuromotor.studies.ground import ground_scene
    from neuromotor.studies.standing import standing_setup

    free = standing_setup(seconds)
    scene = ground_scene(free.ground)
    driven = standing_setup(seconds, balance={"enabled": False}, root="driven")
    sim_jit = compiler.jit(simulate)
    runs = {
        "free": lambda: simulate_contact_jit(free.sim_model, free.params, scene),
        "driven": lambda: sim_jit(driven.sim_model, driven.params),
    }
    n = free.options.n_steps
    out = {"devices": len(jax.devices())}
    for name, fn in runs.items():
        jax.block_until_ready(fn())
        best, before = float("inf"), _switches()
        for _ in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            best = min(best, time.perf_counter() - t0)
        out[name] = {"ms_per_step": 1e3 * best / n, "switches_per_step": (_switches() - before) / (3 * n)}
    print("RESULT " + json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--child", choices=("single", "per-core"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.seconds)
        return
    env = {k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "NPROC", "NEUROMOTOR_CPU_DEVICES")}
    modes = {"single": env, "per-core": {**env, "NEUROMOTOR_CPU_DEVICES": str(os.cpu_count() or 1), "PJRT_NPROC": ""}}
    print(f"{args.seconds:g} s at h = 1/120 s, best of 3 runs per process; per-core = {os.cpu_count()} devices")
    for r in range(args.rounds):
        for mode, menv in modes.items():
            cmd = [sys.executable, __file__, "--child", mode, "--seconds", str(args.seconds)]
            proc = subprocess.run(cmd, env=menv, capture_output=True, text=True, check=True)
            got = json.loads([ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1][7:])
            cells = "  ".join(
                f"{k} {got[k]['ms_per_step']:.3f} ms/step, {got[k]['switches_per_step']:.2f} switches/step"
                for k in ("free", "driven")
            )
            print(f"round {r + 1} {mode:8s} ({got['devices']} device(s)): {cells}")


if __name__ == "__main__":
    main()
