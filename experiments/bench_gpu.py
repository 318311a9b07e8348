"""Speed on a GPU: one trajectory and batched rollouts in float64 and float32, and optionally MJX
beside ours at one batch size (interleaved rounds, :func:`neuromotor.studies.bench_mjx.compare`).

    python experiments/bench_gpu.py [--sizes 256 4096 16384] [--mjx 4096] [--json OUT.json]

Runs on whatever JAX's default backend is (on a CPU it measures the CPU). MJX needs mujoco and
mujoco-mjx installed. Figures: docs/benchmarks.md, "Issue 17: on a GPU".
"""

import argparse
import json

import _common  # noqa: F401


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 4096, 16384])
    ap.add_argument("--mjx", type=int, default=0, help="batch size of the MJX comparison (0: none)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    import jax

    from neuromotor.physics import dynamics as dy
    from neuromotor.studies import bench, bench_mjx

    out = {"jax": jax.__version__, "device": str(jax.devices()[0].device_kind)}
    setup = bench._setup(None, 1.0, "nullspace")
    bsetup = bench._setup(None, 0.25, "nullspace")
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options
    comp, compile_s = bench._compile(lambda m, g, p, ref: dy.rollout(m, g, p, ref, cfg), m, g, p, ref)
    programs = {"rollout": lambda: comp(m, g, p, ref)}
    out["single"] = {"us_per_step": bench._best(programs["rollout"], 5) / cfg.n_steps * 1e6, "compile_s": compile_s}
    print(f"{out['device']}: one trajectory {out['single']['us_per_step']:.1f} us/step, compile {compile_s:.1f} s")
    out["batch"] = []
    for dtype in ("float64", "float32"):
        for row in bench.batched(bsetup, args.sizes, 3, programs, dtype=dtype):
            out["batch"].append(row)
            print(f"  batch {row['batch']:6d} {dtype}: {row['steps_per_s']:12.0f} steps/s, compile {row['compile_s']:.1f} s")
    if args.mjx:
        why = bench_mjx.unavailable()
        if why:
            print(f"MJX: skipped ({why})")
        else:
            mj, data = bench.mujoco_start(setup.character, setup.options.h, setup.ref.theta[0])
            ours = {"rollout": programs["rollout"], "batch": programs[f"batch{args.mjx}"],
                    "batch_float32": programs[f"batch{args.mjx}_float32"]}
            out["mjx"] = bench_mjx.compare(mj, data, ours, steps=cfg.n_steps, batch=args.mjx,
                                           batch_steps=bsetup.options.n_steps, rounds=5)
            bench_mjx.log_figures(out["mjx"])
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
