"""Two questions about the batched step, answered by timing variants of the same rollout in
alternation in one process (batch of pulse magnitudes, branch solver, embedded clip):

    .venv/bin/python experiments/batch_layout.py [--batch 256] [--repeats 15]

* **Where the batch axis sits.** The package's program is ``vmap`` of the whole rollout. Here
  the scan runs outside and each step is vmapped with the batch as the first or as the last
  axis of every array (``in_axes``/``out_axes`` 0 or -1), so that the last-axis variant gives
  XLA:CPU the batch as the minor, contiguous axis of the step's inputs.
* **What the post-stabilization metric costs.** ``S^T M S`` is factored once per step at the
  first Newton iterate. The variant computes it from a fixed pose instead (the reference's first
  state), which XLA can hoist out of the loop: the time it saves bounds what any cheaper metric
  could save. (It changes the motion slightly, so it is a measurement, not a candidate.)

Prints per-trajectory-step times (best and median) and each variant's speed-up over the package's
program as the median of the rounds' ratios.
"""

import argparse
import time

import _common  # noqa: F401
import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args(argv)
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from neuromotor import compiler
    from neuromotor.physics import dynamics as dy
    from neuromotor.physics.solvers import nullspace as ns
    from neuromotor.physics.system import joint_levers, root_lever, world_inertia
    from neuromotor.rotations import quat_to_matrix
    from neuromotor.studies import bench

    setup = bench._setup(None, 0.25, "branch")
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.sim
    scales = jnp.linspace(0.5, 1.5, args.batch)
    params_of = lambda s: dy.Params(g, eqx.tree_at(lambda q: q.magnitude, p, p.magnitude * s))

    def package(scales, ref):
        return jax.vmap(lambda s: dy.rollout(m, g, params_of(s).pulses, ref, cfg).states.quat[1:])(scales)

    def stepwise(axis):
        def run(scales, ref):
            sim = dy.SimModel(m, ref, cfg)
            d0 = jax.vmap(lambda s: dy.init_data(sim, params_of(s)), out_axes=axis)(scales)
            d0 = eqx.tree_at(lambda d: d.k, d0, jnp.asarray(0))
            axes = eqx.tree_at(lambda d: d.k, jax.tree_util.tree_map(lambda _: axis, d0), None,
                               is_leaf=lambda x: x is None)
            step = jax.vmap(lambda s, d: dy.step(sim, params_of(s), d), in_axes=(0, axes), out_axes=axes)

            def body(d, _):
                new = step(scales, d)
                return new, jnp.moveaxis(new.state.quat, axis, 0)

            return jnp.swapaxes(jax.lax.scan(body, d0, None, length=cfg.n_steps)[1], 0, 1)
        return run

    project = ns.NullSpaceSolver.project
    rot0 = quat_to_matrix(ref.init.quat)

    def fixed_metric(self, model, cfg, rot, c, reuse=None):
        st = ns.structure(model.topology, cfg.driven, cfg.free_root, self.unrolled)
        if reuse is None:
            geo0 = ns.geometry(st, *joint_levers(model, rot0), root_lever(model, rot0))
            reuse = ns.projection_metric(st, geo0, model.mass, world_inertia(model, rot0), tree=True)
        return project(self, model, cfg, rot, c, reuse)

    variants = {"package (vmap of the rollout)": (package, project),
                "scan of a step vmapped on axis 0": (stepwise(0), project),
                "scan of a step vmapped on axis -1": (stepwise(-1), project),
                # A function of its own: jit caches traces by function, and this one must be retraced.
                "metric from a fixed pose": (lambda scales, ref: package(scales, ref), fixed_metric)}
    programs, quats = {}, {}
    for name, (fn, proj) in variants.items():
        ns.NullSpaceSolver.project = proj
        try:
            programs[name] = compiler.jit(fn).lower(scales, ref).compile()
        finally:
            ns.NullSpaceSolver.project = project
        quats[name] = np.asarray(jax.block_until_ready(programs[name](scales, ref)))
    base = quats["package (vmap of the rollout)"]
    for name, q in quats.items():
        print(f"{name}: max |quaternion - package's| {np.abs(q - base).max():.1e}")
    times = {name: [] for name in programs}
    for _ in range(args.repeats):
        for name, prog in programs.items():
            t = time.perf_counter()
            jax.block_until_ready(prog(scales, ref))
            times[name].append(time.perf_counter() - t)
    per = args.batch * cfg.n_steps / 1e6
    first = np.array(times["package (vmap of the rollout)"])
    print(f"| variant (batch {args.batch}) | best us / traj-step | median | speed-up (median of rounds) |")
    print("| --- | --- | --- | --- |")
    for name, t in times.items():
        t = np.array(t)
        print(f"| {name} | {t.min() / per:.1f} | {np.median(t) / per:.1f} | {np.median(first / t):.3f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
