#!/usr/bin/env python
"""Benchmark of gain calibration on the 19-joint clip (1 s window, h = 1/120 s).

    python fit/bench_fit.py [configs/fit_synthetic.toml] [--repeats 5] [--reverse] [--json OUT.json]
    python fit/bench_fit.py configs/fit_literature.toml --reverse      # few residuals: reverse mode

Prints:
* compile time of the forward response and of response + Jacobian (first calls);
* one forward evaluation (every case's rollout, vmapped) and one Jacobian of the residual
  (``jax.jacfwd``, 2 tangents; ``--reverse`` adds reverse mode, one backward pass per
  residual, so only for targets with few residuals), median of ``--repeats``,
  and their ratio;
* the wall time of one full calibration (Levenberg-Marquardt from the config's starting
  gains): cold (a fresh process would also pay the compile above) and warm (compiled code
  reused, empty evaluation cache).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp

REPO = pathlib.Path(__file__).resolve().parents[1]


def _persistent_compile_cache():
    # Rollout + Jacobian compiles take minutes; reuse them across runs of this script.
    import jax

    d = os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(REPO / ".jax_cache"))
    jax.config.update("jax_compilation_cache_dir", d)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(REPO / "configs" / "fit_synthetic.toml"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--reverse", action="store_true", help="also time a reverse-mode Jacobian")
    ap.add_argument("--json", default=None, help="write the figures here too")
    args = ap.parse_args(argv)
    _persistent_compile_cache()

    from neuromotor import compiler
    from neuromotor.studies import fit as F
    from neuromotor.io.tables import json_safe, write_json

    t0 = time.perf_counter()
    cal = F.load_calibration(args.config)
    t_setup = time.perf_counter() - t0
    prob = cal.problem
    n_runs = prob.pulses.magnitude.shape[0]
    s = prob.spec
    print(f"config {args.config}: {prob.model.n_dofs} DOFs, {n_runs} rollout(s) of {prob.options.n_steps} steps "
          f"(h = {prob.options.h:.6g} s), window {s.i1 - s.i0} samples, {cal.target.size} residuals")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
          f"JAX backend {jax.default_backend()}, float64 = {jax.config.jax_enable_x64}")

    # Compiled like the fitting layer's Jacobian (neuromotor.compiler), so the ratio compares like with like.
    forward = compiler.jit(lambda p, x: p.outputs(x)[0])
    x0 = jnp.asarray(cal.x0)
    c_fwd, _ = _timed(forward, prob, x0)
    ev = F.ResponseEvaluator(prob, "forward")
    jac_fn = F.compiled_response("forward")
    c_jac, _ = _timed(jac_fn, prob, x0)
    xs = [x0 + 1e-3 * (i + 1) for i in range(args.repeats)]
    # Interleaved, so that load from other processes hits both alike; the ratio is the median
    # of the per-pair ratios.
    pairs = [(_timed(forward, prob, x)[0], _timed(jac_fn, prob, x)[0]) for x in xs]
    t_fwd = statistics.median(p[0] for p in pairs)
    t_jac = statistics.median(p[1] for p in pairs)
    ratio = statistics.median(p[1] / p[0] for p in pairs)
    figures = {
        "config": args.config, "n_dofs": prob.model.n_dofs, "rollouts": n_runs, "steps": prob.options.n_steps,
        "h": prob.options.h, "residuals": int(cal.target.size), "setup_s": t_setup,
        "compile_forward_s": c_fwd, "compile_jacfwd_s": c_jac,
        "forward_s": t_fwd, "jacfwd_s": t_jac, "jacfwd_over_forward": ratio,
    }
    print(f"setup (clip, inverse dynamics, target): {t_setup:.2f} s")
    print(f"compile: forward {c_fwd:.1f} s, response + jacfwd {c_jac:.1f} s")
    print(f"one forward evaluation ({n_runs} rollouts): {t_fwd * 1e3:.1f} ms")
    print(f"one jacfwd Jacobian of the residual:   {t_jac * 1e3:.1f} ms  = {ratio:.2f} x forward "
          f"(median of {len(pairs)} interleaved pairs)")
    if args.reverse and cal.target.size > 200:
        print(f"reverse mode skipped: {cal.target.size} residuals = {cal.target.size} backward passes "
              f"(use it with feature targets, e.g. configs/fit_literature.toml)")
    elif args.reverse:
        rev_fn = F.compiled_response("reverse")
        c_rev, _ = _timed(rev_fn, prob, x0)
        rpairs = [(_timed(forward, prob, x)[0], _timed(rev_fn, prob, x)[0]) for x in xs]
        t_rev = statistics.median(p[1] for p in rpairs)
        rratio = statistics.median(p[1] / p[0] for p in rpairs)
        figures.update(compile_reverse_s=c_rev, reverse_s=t_rev, reverse_over_forward=rratio)
        print(f"compile response + reverse-mode Jacobian {c_rev:.1f} s; one reverse Jacobian {t_rev * 1e3:.1f} ms "
              f"= {rratio:.2f} x forward")

    # Full calibration. Cold: the first fit in this process (solver step compile included,
    # response compile already paid above). Warm: a second identical fit, empty cache.
    res_cold, _ = F.calibrate(cal, None, progress=True, evaluator=ev)
    ev2 = ev.with_problem(prob)
    res_warm, _ = F.calibrate(cal, None, progress=True, evaluator=ev2)
    figures.update(
        fit_solver=res_warm.solver, fit_status=res_warm.status, fit_iterations=res_warm.iterations,
        fit_evaluations=res_warm.evaluations, fit_cold_s=res_cold.wall_time_s, fit_warm_s=res_warm.wall_time_s,
        fit_cold_with_compile_s=res_cold.wall_time_s + c_jac, ks=res_warm.ks, kd=res_warm.kd,
        se_ks=res_warm.se_ks, se_kd=res_warm.se_kd,
    )
    print(f"full calibration ({res_warm.solver}, {res_warm.iterations} iterations, {res_warm.evaluations} "
          f"evaluations, {res_warm.status}): warm {res_warm.wall_time_s:.2f} s, cold {res_cold.wall_time_s:.2f} s "
          f"(+ {c_jac:.1f} s response compile = {res_cold.wall_time_s + c_jac:.1f} s in a fresh process)")
    print(f"fitted ks = {res_warm.ks:.5g} +- {res_warm.se_ks:.2g} 1/s^2, kd = {res_warm.kd:.5g} +- {res_warm.se_kd:.2g} 1/s")
    if args.json:
        write_json(args.json, json_safe(figures))
        print(f"wrote {args.json}")
    return 0 if res_warm.converged else 1


if __name__ == "__main__":
    sys.exit(main())
