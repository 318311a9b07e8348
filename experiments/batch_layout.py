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
* **Other post-stabilizations** (each changes the method): the metric taken from Eq. 2's own
  factored matrix ``S^T A S`` at t_k (no second factorization; the right-hand side
  ``S^T A dx_p``, a projection at every Newton step), one Newton step instead of two, and a
  second Newton step that projects again (a fresh metric) instead of the package's closing step.

Prints, per variant, how far its quaternions and its largest constraint violation are from the
package's, then per-trajectory-step times (best and median) and its speed-up over the package's
program as the median of the rounds' ratios.
"""

import argparse
import dataclasses
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
    from neuromotor.physics import constraints as cs
    from neuromotor.physics import dynamics as dy
    from neuromotor.physics import solvers
    from neuromotor.physics.solvers import branch
    from neuromotor.physics.solvers import nullspace as ns
    from neuromotor.physics.system import joint_levers, retract, root_lever, world_inertia
    from neuromotor.rotations import quat_to_matrix
    from neuromotor.studies import bench

    setup = bench._setup(None, 0.25, "branch")
    m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options
    scales = jnp.linspace(0.5, 1.5, args.batch)
    params_of = lambda s: dy.Params(g, eqx.tree_at(lambda q: q.magnitude, p, p.magnitude * s))

    def package(scales, ref, cfg=cfg):
        run = jax.vmap(lambda s: dy.rollout(m, g, params_of(s).pulses, ref, cfg))(scales)
        return run.states.quat[:, 1:], run.violation

    def system_metric_step(sim, params, data):
        """dy.step with each Newton step ``dx_p + S w``, ``(S^T A S) w = -S^T A dx_p`` from Eq. 2's factor."""
        solver = solvers.get(sim.options.solver)
        eq = dy.equations_of_motion(sim, params, data, solver)
        v_new, aux = solver.solve(eq.system, eq.r, eq.b)
        lam, residual = solver.multipliers(eq.system, eq.r, eq.b, v_new, aux)
        st, red, targets = eq.system.st, eq.system.reduced, sim.ref.pose_targets(data.k + 1)
        pos, quat = retract(data.state.pos, data.state.quat, sim.options.h * v_new)
        for i in range(sim.options.stabilization_steps + 1):
            rot = quat_to_matrix(quat)
            c = cs.full_constraint_error(m, sim.options.driven, pos, rot, targets, sim.options.free_root)
            if i == sim.options.stabilization_steps:  # the last error is the violation left
                break
            geo = ns.geometry(st, *joint_levers(m, rot), root_lever(m, rot))
            x_p = ns.particular_correction(st, geo, c)
            rhs = -ns.project_forces(st, geo, eq.system.a_times(x_p))
            w = branch.linear_solve(st.tree, red.paths, red.factor, rhs[3:].reshape(-1, 3))
            pos, quat = retract(pos, quat, x_p + ns.apply_basis(st, geo, jnp.concatenate([jnp.zeros(6, c.dtype),
                                                                                          w[1:].reshape(-1)])))
        info = dy.StepInfo(residual, jnp.max(jnp.abs(c)), eq.force, eq.points, lam / sim.options.h, eq.reflex)
        return dy.Data(data.k + 1, dy.State(pos, quat, v_new[:, :3], v_new[:, 3:]), info, eq.history)

    def system_metric(scales, ref):
        def one(s):
            sim, params = dy.SimModel(m, ref, cfg), params_of(s)
            out = dy.scan_steps(sim, params, dy.init_data(sim, params), step_fn=system_metric_step)[0]
            return out.state.quat, out.info.violation
        return jax.vmap(one)(scales)

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
                return new, (jnp.moveaxis(new.state.quat, axis, 0), jnp.moveaxis(new.info.violation, axis, 0))

            quat, violation = jax.lax.scan(body, d0, None, length=cfg.n_steps)[1]
            return jnp.swapaxes(quat, 0, 1), violation.T
        return run

    rot0 = quat_to_matrix(ref.init.quat)

    projection_metric = ns.projection_metric

    def fixed_metric(st, geo, mass, inertia_world, tree=False):
        geo0 = ns.geometry(st, *joint_levers(m, rot0), root_lever(m, rot0))
        return projection_metric(st, geo0, mass, world_inertia(m, rot0), tree)

    def second_projection(model, cfg, rot, c, unrolled=False):
        return solvers.get(cfg.solver).projection_step(model, cfg, rot, c)

    one_newton = dataclasses.replace(cfg, stabilization_steps=1)
    # name: (program, patches (owner, attribute, value) while it is traced). Patched variants get
    # functions of their own: jit caches traces by function, and these must be retraced.
    variants = {"package (vmap of the rollout)": (package, ()),
                "scan of a step vmapped on axis 0": (stepwise(0), ()),
                "scan of a step vmapped on axis -1": (stepwise(-1), ()),
                "metric from a fixed pose": (lambda scales, ref: package(scales, ref),
                                             ((ns, "projection_metric", fixed_metric),)),
                "metric: Eq. 2's factored S^T A S at t_k": (system_metric, ()),
                "one Newton step": (lambda scales, ref: package(scales, ref, one_newton), ()),
                "second Newton step a projection too": (lambda scales, ref: package(scales, ref),
                                                        ((cs, "closing_step", second_projection),))}
    programs, quats = {}, {}
    for name, (fn, patches) in variants.items():
        saved = [(owner, attr, getattr(owner, attr)) for owner, attr, _ in patches]
        for owner, attr, value in patches:
            setattr(owner, attr, value)
        try:
            programs[name] = compiler.jit(fn).lower(scales, ref).compile()
        finally:
            for owner, attr, value in saved:
                setattr(owner, attr, value)
        quats[name] = [np.asarray(x) for x in jax.block_until_ready(programs[name](scales, ref))]
    base = quats["package (vmap of the rollout)"][0]
    for name, (q, violation) in quats.items():
        print(f"{name}: max |quaternion - package's| {np.abs(q - base).max():.1e}, "
              f"max constraint violation {violation.max():.1e} m")
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
