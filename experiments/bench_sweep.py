"""Sweep throughput: simulated seconds per wall second, summed over the batch, on the 19-joint clip.

    .venv/bin/python experiments/bench_sweep.py [--sizes 1 8 64 256] [--duration 0.25] [--devices 2]

Modes, each timed after a warm-up call (compile excluded, printed separately):

* ``map``: the sweep program (neuromotor.studies.sweep.Sweeper): batch sharded over the devices with
  shard_map, a lax.map loop of rollouts inside each shard;
* ``vmap``: the same program with ``inner_batch`` = the whole shard, i.e. one vmapped rollout
  per device;
* ``loop``: a Python loop of single jitted rollouts (simulate.simulate_jit), the baseline.

``--devices N`` forces N host CPU devices (XLA_FLAGS) before JAX starts.
"""

import argparse
import math
import os
import sys
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 8, 64, 256])
    ap.add_argument("--duration", type=float, default=0.25, help="simulated seconds per run")
    ap.add_argument("--devices", type=int, default=0, help="force this many host CPU devices")
    ap.add_argument("--modes", nargs="+", default=["map", "vmap", "loop"], choices=["map", "vmap", "loop"])
    ap.add_argument("--loop-runs", type=int, default=8, help="single runs timed for the loop baseline")
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per case; the best is reported")
    args = ap.parse_args(argv)
    if args.devices:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                                   f" --xla_force_host_platform_device_count={args.devices}").strip()
    import _common  # noqa: F401  (float64; compile cache)
    import jax
    import numpy as np

    from neuromotor.config import DEFAULT_HIT, SimulationConfig
    from neuromotor.studies.simulate import body_lookup, prepare, simulate_jit
    from neuromotor.studies.sweep import GainSetting, SweepSpec, Sweeper, build_batch

    hit = dict(DEFAULT_HIT, start=0.05)
    setup = prepare(SimulationConfig(duration=args.duration, perturbations=[hit]))
    sim_s = setup.options.n_steps * setup.options.h
    devices = jax.devices()
    print(f"# {len(devices)} x {devices[0].platform} device(s), {os.cpu_count()} CPU cores, float64; "
          f"19-joint clip, {setup.options.n_steps} steps of {setup.options.h:.5f} s ({sim_s:.3f} s simulated per run)")
    index = body_lookup(setup.model)

    def batch_of(n):
        mags = list(np.linspace(50.0, 400.0, n))
        runs = SweepSpec(mags, [GainSetting(400.0, 20.0)]).runs(hit)
        return build_batch(setup.gains, setup.pulses, runs, index, setup.options.h, setup.model)

    print(f"{'mode':<6} {'batch':>6} {'compile s':>10} {'wall s':>9} {'sim s / wall s':>15} {'ms per run':>11}")
    results = {}
    for mode in [m for m in args.modes if m != "loop"]:
        for n in args.sizes:
            per_dev = -(-n // len(devices))
            sweeper = Sweeper(setup.model, setup.ref, setup.options, chunk=n,
                              inner_batch=per_dev if mode == "vmap" else 1)
            batch = sweeper.pad(batch_of(n), 0, n)
            t0 = time.perf_counter()
            jax.block_until_ready(sweeper.simulate_chunk(batch))
            t1 = time.perf_counter()
            compile_s = t1 - t0
            wall = math.inf
            for _ in range(args.repeat):  # best of several: the machine is shared
                t2 = time.perf_counter()
                jax.block_until_ready(sweeper.simulate_chunk(batch))
                wall = min(wall, time.perf_counter() - t2)
            results[(mode, n)] = wall
            print(f"{mode:<6} {n:>6} {compile_s - wall:>10.1f} {wall:>9.3f} {n * sim_s / wall:>15.2f} "
                  f"{1e3 * wall / n:>11.1f}", flush=True)
    if "loop" in args.modes:
        import dataclasses

        batch = batch_of(args.loop_runs)
        t0 = time.perf_counter()
        p0 = dataclasses.replace(setup.pulses, magnitude=batch.pulses.magnitude[0])
        jax.block_until_ready(simulate_jit(setup.sim_model, dataclasses.replace(setup.params, pulses=p0)).theta)
        t1 = time.perf_counter()
        per_run = math.inf
        for _ in range(args.repeat):
            t2 = time.perf_counter()
            for i in range(args.loop_runs):
                p = dataclasses.replace(setup.pulses, magnitude=batch.pulses.magnitude[i])
                jax.block_until_ready(simulate_jit(setup.sim_model, dataclasses.replace(setup.params, pulses=p)).theta)
            per_run = min(per_run, (time.perf_counter() - t2) / args.loop_runs)
        print(f"{'loop':<6} {args.loop_runs:>6} {t1 - t0 - per_run:>10.1f} {per_run * args.loop_runs:>9.3f} "
              f"{sim_s / per_run:>15.2f} {1e3 * per_run:>11.1f}", flush=True)
        for (mode, n), wall in sorted(results.items()):
            print(f"speed-up of {mode} at batch {n} over a Python loop of {n} single runs: "
                  f"{per_run * n / wall:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
