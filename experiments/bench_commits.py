"""Speed of the working tree against an earlier commit, timed in alternation in one process.

    .venv/bin/python experiments/bench_commits.py REV [--batch 1] [--repeats 15] [--solver branch] [--rev-solver branch]
        [--jacobians jacfwd] [--seconds 1.0] [--gain-jacobian] [--rates] [--free]

The host's speed drifts by 2x between runs minutes apart, so two separate benchmark runs cannot
resolve a 10 % change. This script extracts ``src/neuromotor`` of commit REV (``git archive``)
into a temporary folder as the package ``neuromotor_at_rev``, compiles the default 1 s rollout of
both versions on the embedded clip (one trajectory, or ``--batch N`` pulse magnitudes under
``vmap``), checks that they compute the same joint angles, and times the two alternately
(``--gain-jacobian``: ``jax.jacfwd`` of the joint angles over (ks, kd) instead, as in
``neuromotor bench``; ``--rates``: the joint rates theta_dot returned beside the angles, as
sweeps that write them and the acceleration targets of ``fit`` use them; ``--free``: the free root
standing on the ground with its balance loop, issue 38, instead of the driven rollout; with ``--batch N``
N of them under ``vmap`` by ``--solver``). The best of each is
printed, in microseconds per trajectory-step, and the speedup both as the ratio of the bests and
as the median of the rounds' ratios (the steadier of the two when the host drifts within the run).
"""

import argparse
import dataclasses
import importlib
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _extract(rev: str, dest: Path) -> str:
    """``src/neuromotor`` at ``rev`` as the importable package ``neuromotor_at_rev`` under dest."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "src/neuromotor"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    pkg = dest / "neuromotor_at_rev"
    (dest / "src" / "neuromotor").rename(pkg)
    # Absolute imports inside the copy must resolve to the copy, not to the working tree.
    for path in pkg.rglob("*.py"):
        text = path.read_text()
        text = re.sub(r"\b(from|import) neuromotor\b", r"\1 neuromotor_at_rev", text)
        path.write_text(re.sub(r"\bneuromotor\.(?=[a-z_])", "neuromotor_at_rev.", text))
    return "neuromotor_at_rev"


def _module(pkg: str, *names: str):
    """The first of ``names`` that imports from ``pkg`` (commits before the subpackage layout
    kept every module at the top level)."""
    for name in names:
        try:
            return importlib.import_module(f"{pkg}.{name}")
        except ModuleNotFoundError:
            continue
    raise ModuleNotFoundError(f"none of {names} in {pkg}")


def _program(pkg: str, batch: int, solver: str = "nullspace", jacobians: str | None = None, seconds: float = 1.0,
             gain_jacobian: bool = False, rates: bool = False):
    """(zero-argument compiled call, its joint angles, trajectory-steps per call)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    bench = _module(pkg, "studies.bench", "bench")
    dy = _module(pkg, "physics.dynamics", "dynamics")
    compiler = importlib.import_module(f"{pkg}.compiler")
    setup = bench._setup(None, seconds, solver)
    # The step's options: Setup.options (issue 36), Setup.sim before it.
    options = setup.options if hasattr(setup, "options") else setup.sim  # Setup.sim before issue 36
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, options
    if jacobians is not None:
        cfg = dataclasses.replace(cfg, jacobians=jacobians)
    scales = jnp.linspace(0.5, 1.5, batch)
    gains_mod = _module(pkg, "studies.gains")  # gains_for (issue 36), set_gains before it
    set_gains = getattr(gains_mod, "set_gains", None) or (lambda g, ks, kd: gains_mod.gains_for(g, ks=ks, kd=kd))

    def many(scales, g, ref):
        def one(s, g):
            run = dy.rollout(m, g, eqx.tree_at(lambda q: q.magnitude, p, p.magnitude * s), ref, cfg)
            return jnp.concatenate([run.theta, run.theta_dot], -1) if rates else run.theta
        if gain_jacobian:
            one = lambda s, g, one=one: jax.jacfwd(lambda x: one(s, set_gains(g, x[0], x[1])))(jnp.stack([g.ks, g.kd]))
        return jax.vmap(one, (0, None))(scales, g) if batch > 1 else one(scales[0], g)[None]

    fn = compiler.jit(many)
    start = time.perf_counter()
    theta = jax.block_until_ready(fn(scales, g, ref))
    print(f"{pkg}: trace and compile {time.perf_counter() - start:.1f} s")
    return (lambda: fn(scales, g, ref)), theta, batch * cfg.n_steps


def _free_program(pkg: str, seconds: float, batch: int = 1, solver: str = "nullspace"):
    """(zero-argument compiled call, its body positions, trajectory-steps per call) of the
    free-standing rollout on the ground (issue 38): ``standing_setup``'s pose, balance on; one
    trajectory, or ``batch`` of them under ``vmap`` (the ankle gain scaled from 0.8 to 1.2, the
    ``solver`` of the batch)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    standing = _module(pkg, "studies.standing")
    ground = _module(pkg, "studies.ground")
    contact = _module(pkg, "physics.contact")
    compiler = importlib.import_module(f"{pkg}.compiler")
    s = standing.standing_setup(seconds)
    scene = ground.ground_scene(s.ground)
    sim = s.sim_model
    if batch > 1:
        sim = eqx.tree_at(lambda q: q.options, sim, dataclasses.replace(sim.options, solver=solver))
    scales = jnp.linspace(0.8, 1.2, batch)

    def many(sim, params, scales):
        def one(c):
            p = eqx.tree_at(lambda q: q.gains.balance.kp, params, params.gains.balance.kp * c)
            return contact.simulate_contact(sim, p, scene).run.states.pos
        return jax.vmap(one)(scales) if batch > 1 else one(scales[0])[None]

    fn = compiler.jit(many)
    start = time.perf_counter()
    pos = jax.block_until_ready(fn(sim, s.params, scales))
    print(f"{pkg}: trace and compile {time.perf_counter() - start:.1f} s")
    return (lambda: fn(sim, s.params, scales)), pos, batch * s.options.n_steps


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rev", help="the commit to compare with (e.g. HEAD~1)")
    ap.add_argument("--batch", type=int, default=1, help="trajectories per call (vmap over pulse magnitude)")
    ap.add_argument("--repeats", type=int, default=15, help="timed calls of each version")
    ap.add_argument("--solver", default="nullspace", help="solver of the working tree")
    ap.add_argument("--rev-solver", default="nullspace", help="solver of REV (commits before 10bfa6f have no 'branch')")
    ap.add_argument("--jacobians", default=None, help="StepOptions.jacobians of the working tree (closed_form, jacfwd)")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated seconds per rollout (neuromotor bench's batches: 0.25)")
    ap.add_argument("--gain-jacobian", action="store_true", help="time jacfwd over (ks, kd) instead of the rollout")
    ap.add_argument("--rates", action="store_true", help="return the joint rates beside the angles")
    ap.add_argument("--free", action="store_true", help="the free-standing rollout on the ground instead (issue 38)")
    args = ap.parse_args(argv)
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        old_pkg = _extract(args.rev, Path(tmp))
        runs = {}
        for name, pkg, solver, jac in (("working tree", "neuromotor", args.solver, args.jacobians),
                                       (args.rev, old_pkg, args.rev_solver, None)):
            if args.free:
                runs[name] = _free_program(pkg, args.seconds, args.batch, solver)
            else:
                runs[name] = _program(pkg, args.batch, solver, jac, args.seconds, args.gain_jacobian, args.rates)
        (new, th_new, steps), (old, th_old, _) = runs.values()
        what = ("theta, theta_dot" if args.rates else "theta")
        what = f"d({what}) / d(ks, kd)" if args.gain_jacobian else "body positions" if args.free else what
        print(f"max |{what}: working tree - {args.rev}|: {float(jnp.max(jnp.abs(th_new - th_old))):.2e}")
        times = {name: [] for name in runs}
        for _ in range(args.repeats):
            for name, (call, _, _) in runs.items():
                t = time.perf_counter()
                jax.block_until_ready(call())
                times[name].append(time.perf_counter() - t)
        for name, t in times.items():
            print(f"{name:>14}: {min(t) / steps * 1e6:8.1f} us per trajectory-step (batch {args.batch}, best)")
        new_t, old_t = (np.array(t) for t in times.values())
        print(f"speedup of the working tree: {old_t.min() / new_t.min():.3f}x (best of each), "
              f"{np.median(old_t / new_t):.3f}x (median of the rounds' ratios)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
